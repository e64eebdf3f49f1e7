//! Pinhole camera: intrinsics, undistortion, the image line → plane normal step (Eq. 1).

use nalgebra::{Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Pinhole intrinsics (pixels) with OpenCV's plumb-bob distortion `[k1, k2, p1, p2, k3]`.
///
/// Also the intrinsics object of the calibration files (`hw_io::calib_files`): unknown keys
/// are refused, `skew` and `distortion` default to zero.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Intrinsics {
    /// Focal length along u, pixels.
    pub fx: f64,
    /// Focal length along v, pixels.
    pub fy: f64,
    /// Principal point u, pixels.
    pub cx: f64,
    /// Principal point v, pixels.
    pub cy: f64,
    /// Skew `K[0][1]`, pixels (0 for every modern camera).
    #[serde(default)]
    pub skew: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Plumb-bob distortion `[k1, k2, p1, p2, k3]` (dimensionless); zeros for none.
    #[serde(default)]
    pub distortion: [f64; 5],
}

/// Why intrinsics are unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IntrinsicsError {
    /// A focal length is not finite and positive.
    #[error("focal lengths must be finite and positive (fx = {fx}, fy = {fy})")]
    Focal {
        /// fx, pixels.
        fx: f64,
        /// fy, pixels.
        fy: f64,
    },
    /// The principal point, skew or a distortion coefficient is not finite.
    #[error("principal point, skew and distortion must be finite")]
    NotFinite,
    /// Zero image size.
    #[error("image size must be positive (got {width}x{height})")]
    Size {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
}

impl Intrinsics {
    /// Checks that the intrinsics are finite and usable.
    pub fn validate(&self) -> Result<(), IntrinsicsError> {
        if !(self.fx.is_finite() && self.fx > 0.0 && self.fy.is_finite() && self.fy > 0.0) {
            return Err(IntrinsicsError::Focal { fx: self.fx, fy: self.fy });
        }
        if ![self.cx, self.cy, self.skew].iter().chain(self.distortion.iter()).all(|v| v.is_finite()) {
            return Err(IntrinsicsError::NotFinite);
        }
        if self.width == 0 || self.height == 0 {
            return Err(IntrinsicsError::Size { width: self.width, height: self.height });
        }
        Ok(())
    }

    /// The camera matrix `K` (pixels).
    pub fn k(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, self.skew, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// `K⁻¹` (valid intrinsics only).
    pub fn k_inv(&self) -> Matrix3<f64> {
        let (fx, fy, s, cx, cy) = (self.fx, self.fy, self.skew, self.cx, self.cy);
        Matrix3::new(1.0 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy), 0.0, 1.0 / fy, -cy / fy, 0.0, 0.0, 1.0)
    }

    /// True when every distortion coefficient is zero.
    pub fn is_undistorted(&self) -> bool {
        self.distortion.iter().all(|d| *d == 0.0)
    }

    /// Projects a point in the camera frame (metres, z > 0) to distorted pixels.
    pub fn project(&self, p_c: &Vector3<f64>) -> Vector2<f64> {
        let x = p_c.x / p_c.z;
        let y = p_c.y / p_c.z;
        let (xd, yd) = self.distort(x, y);
        Vector2::new(self.fx * xd + self.skew * yd + self.cx, self.fy * yd + self.cy)
    }

    /// Ideal (undistorted) pixel → measured (distorted) pixel: the inverse of
    /// [`Self::undistort_px`].
    pub fn distort_px(&self, px: &Vector2<f64>) -> Vector2<f64> {
        if self.is_undistorted() {
            return *px;
        }
        let n = self.k_inv() * Vector3::new(px.x, px.y, 1.0);
        let (xd, yd) = self.distort(n.x, n.y);
        Vector2::new(self.fx * xd + self.skew * yd + self.cx, self.fy * yd + self.cy)
    }

    fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.distortion;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Removes lens distortion from a measured pixel (fixed-point iteration, as OpenCV's
    /// `undistortPoints`); returns the ideal pinhole pixel. Identity without distortion.
    pub fn undistort_px(&self, px: &Vector2<f64>) -> Vector2<f64> {
        if self.is_undistorted() {
            return *px;
        }
        let n = self.k_inv() * Vector3::new(px.x, px.y, 1.0);
        let (x0, y0) = (n.x, n.y);
        let (mut x, mut y) = (x0, y0);
        for _ in 0..20 {
            let (xd, yd) = self.distort(x, y);
            x -= xd - x0;
            y -= yd - y0;
        }
        Vector2::new(self.fx * x + self.skew * y + self.cx, self.fy * y + self.cy)
    }

    /// True when a pixel lies inside the image.
    pub fn in_image(&self, px: &Vector2<f64>) -> bool {
        px.x >= 0.0 && px.y >= 0.0 && px.x <= self.width as f64 - 1.0 && px.y <= self.height as f64 - 1.0
    }
}

/// Why a line cannot give a plane normal.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum LineError {
    /// A coordinate is NaN or infinite.
    #[error("line point is not finite")]
    NotFinite,
    /// The two points coincide (closer than 1e-6 pixel): no line.
    #[error("the two line points coincide")]
    Coincident,
}

/// Eq. 1: the unit normal, in the camera frame, of the plane through the optical centre and
/// the image line through pixels `p` and `q` (ideal, undistorted pixels).
///
/// `n = (K⁻¹p̃ × K⁻¹q̃) / |·|` — the paper's `[p; f] × [q; f]` for square pixels and centred
/// coordinates, normalised so every observation weighs the same in Eq. 5 and Eq. 8.
pub fn plane_normal(k_inv: &Matrix3<f64>, p: &Vector2<f64>, q: &Vector2<f64>) -> Result<Vector3<f64>, LineError> {
    if !(p.x.is_finite() && p.y.is_finite() && q.x.is_finite() && q.y.is_finite()) {
        return Err(LineError::NotFinite);
    }
    if (p - q).norm() < 1e-6 {
        return Err(LineError::Coincident);
    }
    let a = k_inv * Vector3::new(p.x, p.y, 1.0);
    let b = k_inv * Vector3::new(q.x, q.y, 1.0);
    let n = a.cross(&b);
    let norm = n.norm();
    if !(norm > 0.0 && norm.is_finite()) {
        return Err(LineError::Coincident);
    }
    Ok(n / norm)
}

/// Signed distance (pixels) from pixel `u` to the image line `l` (homogeneous pixel line,
/// `l·(u, v, 1) = 0`); NaN-free only for `l` with `(l0, l1) ≠ 0`.
pub fn point_line_distance_px(l: &Vector3<f64>, u: &Vector2<f64>) -> f64 {
    (l.x * u.x + l.y * u.y + l.z) / (l.x * l.x + l.y * l.y).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> Intrinsics {
        Intrinsics {
            fx: 500.0,
            fy: 510.0,
            cx: 320.0,
            cy: 240.0,
            skew: 0.5,
            width: 640,
            height: 480,
            distortion: [-0.2, 0.05, 0.001, -0.002, 0.0],
        }
    }

    #[test]
    fn k_inv_inverts_k() {
        let c = cam();
        assert!((c.k() * c.k_inv() - Matrix3::identity()).norm() < 1e-14);
    }

    #[test]
    fn undistort_inverts_projection() {
        let c = cam();
        let p = Vector3::new(0.02, -0.015, 0.08);
        let px = c.project(&p);
        let ideal = c.undistort_px(&px);
        let pin = c.k() * (p / p.z);
        assert!((ideal - Vector2::new(pin.x, pin.y)).norm() < 1e-9, "{ideal} vs {pin}");
    }

    #[test]
    fn plane_normal_is_orthogonal_to_the_3d_line() {
        let mut c = cam();
        c.distortion = [0.0; 5];
        // A 3-D line in the camera frame; the plane through the centre and the line.
        let a = Vector3::new(0.01, 0.02, 0.1);
        let d = Vector3::new(0.3, -0.5, 0.2).normalize();
        let b = a + d * 0.05;
        let n = plane_normal(&c.k_inv(), &c.project(&a), &c.project(&b)).unwrap();
        assert!((n.norm() - 1.0).abs() < 1e-12);
        assert!(n.dot(&a).abs() < 1e-12 && n.dot(&d).abs() < 1e-12);
        let same = Vector2::new(3.0, 4.0);
        assert_eq!(plane_normal(&c.k_inv(), &same, &same), Err(LineError::Coincident));
        let nan = Vector2::new(f64::NAN, 4.0);
        assert_eq!(plane_normal(&c.k_inv(), &nan, &same), Err(LineError::NotFinite));
    }
}
