//! The shaft's projected axis from its two contour lines.
//!
//! A cylinder (the instrument shaft, axis through `A` with direction `d`, radius `r`) seen by a
//! pinhole camera has two contour lines: the images of the two planes through the optical
//! centre tangent to the cylinder. The plane through the optical centre and the axis
//! **bisects** the two tangent planes (both tangent planes are at the same angle from it, by
//! the cylinder's symmetry about that plane). So, with each contour line `l` (`l·x = 0` for the
//! homogeneous pixels `x` on it) lifted to its plane normal `n = Kᵀ·l` and normalised in 3-D,
//! both oriented with the shaft's inside positive, the axis plane's normal is `n₁ − n₀`, and
//! the projected axis is `K⁻ᵀ·(n₁ − n₀)` (positive on contour 0's side: there `n₀·X = 0` and
//! `n₁·X > 0`) ([`axis_from_contours`]).
//!
//! The calibration paper takes the *middle line* of the two image lines instead
//! ([`middle_line`]: the bisector in the image, `l₁ − l₀` with each line normalised in the
//! image). It is the axis only when the shaft lies in a plane parallel to the image (both
//! tangent planes equally inclined in the image too); otherwise, under perspective, the middle
//! line leaves the axis by up to several pixels for a shaft near the lens or the image border,
//! as that paper notes.

use nalgebra::{Matrix3, Vector3};

/// An image line `a·u + b·v + c = 0`, undistorted pixels, with `a² + b² = 1` (so `a·u + b·v + c`
/// is the signed distance in pixels).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageLine {
    /// `[a, b, c]`.
    pub abc: [f64; 3],
}

/// Why a line could not be formed.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum LineError {
    /// A coefficient is NaN or infinite.
    #[error("a line coefficient is not finite")]
    NotFinite,
    /// `a = b = 0`: not a line.
    #[error("a = b = 0: not a line")]
    Degenerate,
    /// The two contours give no axis: they are the same line (or the same plane), or the
    /// camera matrix is singular.
    #[error("the two contour lines give no axis (identical lines, or a singular camera matrix)")]
    NoAxis,
    /// The interior point is on a contour line: the inside cannot be told.
    #[error("the interior point lies on a contour line")]
    InteriorOnLine,
}

impl ImageLine {
    /// The line `[a, b, c]` scaled to `a² + b² = 1`.
    pub fn new(abc: [f64; 3]) -> Result<Self, LineError> {
        if !abc.iter().all(|v| v.is_finite()) {
            return Err(LineError::NotFinite);
        }
        let n = abc[0].hypot(abc[1]);
        if n < 1e-300 {
            return Err(LineError::Degenerate);
        }
        Ok(Self { abc: abc.map(|v| v / n) })
    }

    /// Signed distance of pixel `(u, v)` from the line, pixels.
    pub fn distance_px(&self, u: f64, v: f64) -> f64 {
        self.abc[0] * u + self.abc[1] * v + self.abc[2]
    }

    /// The same line with the opposite sign (the other side positive).
    pub fn flipped(&self) -> Self {
        Self { abc: self.abc.map(|v| -v) }
    }

    /// The line with pixel `(u, v)` on its positive side.
    fn oriented(self, u: f64, v: f64) -> Result<Self, LineError> {
        let d = self.distance_px(u, v);
        if d.abs() < 1e-12 {
            return Err(LineError::InteriorOnLine);
        }
        Ok(if d > 0.0 { self } else { self.flipped() })
    }
}

/// The exact projected axis of a cylinder from its two contour lines (undistorted pixels) and
/// the camera matrix `k` (pixels). `interior_px` is any pixel between the two contours (the
/// shaft's inside; e.g. the midpoint of two detected edge points): it orients both lines.
/// The result has the contour `c0`'s side positive.
pub fn axis_from_contours(
    k: &Matrix3<f64>,
    c0: &ImageLine,
    c1: &ImageLine,
    interior_px: [f64; 2],
) -> Result<ImageLine, LineError> {
    let [u, v] = interior_px;
    let (c0, c1) = (c0.oriented(u, v)?, c1.oriented(u, v)?);
    let plane = |l: &ImageLine| -> Result<Vector3<f64>, LineError> {
        let n = k.transpose() * Vector3::from(l.abc);
        let norm = n.norm();
        if !(norm.is_finite() && norm > 1e-300) {
            return Err(LineError::NoAxis);
        }
        Ok(n / norm)
    };
    let n_axis = plane(&c1)? - plane(&c0)?;
    if n_axis.norm() < 1e-12 {
        return Err(LineError::NoAxis);
    }
    let k_inv_t = k.try_inverse().ok_or(LineError::NoAxis)?.transpose();
    let l = k_inv_t * n_axis;
    let axis = ImageLine::new([l.x, l.y, l.z]).map_err(|_| LineError::NoAxis)?;
    Ok(axis)
}

/// The middle line of the two contour lines in the image (the calibration paper's
/// centreline): the bisector `l₁ − l₀` of the two lines, each normalised in the image and
/// oriented with `interior_px` positive. Positive on `c0`'s side.
pub fn middle_line(c0: &ImageLine, c1: &ImageLine, interior_px: [f64; 2]) -> Result<ImageLine, LineError> {
    let [u, v] = interior_px;
    let (c0, c1) = (c0.oriented(u, v)?, c1.oriented(u, v)?);
    let l = [c1.abc[0] - c0.abc[0], c1.abc[1] - c0.abc[1], c1.abc[2] - c0.abc[2]];
    ImageLine::new(l).map_err(|_| LineError::NoAxis)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k() -> Matrix3<f64> {
        Matrix3::new(400.0, 0.0, 319.5, 0.0, 400.0, 239.5, 0.0, 0.0, 1.0)
    }

    #[test]
    fn a_shaft_parallel_to_the_image_has_its_axis_on_the_middle_line() {
        // Vertical contours at u = 300 and u = 340, the shaft in a fronto-parallel plane in
        // front of the principal point: both constructions give u = 320... up to the
        // perspective of the tangent planes, which is symmetric only about the optical axis.
        let c0 = ImageLine::new([1.0, 0.0, -299.5]).unwrap();
        let c1 = ImageLine::new([1.0, 0.0, -339.5]).unwrap();
        let axis = axis_from_contours(&k(), &c0, &c1, [319.5, 100.0]).unwrap();
        let mid = middle_line(&c0, &c1, [319.5, 100.0]).unwrap();
        assert!(axis.distance_px(319.5, 0.0).abs() < 1e-9);
        assert!(mid.distance_px(319.5, 0.0).abs() < 1e-9);
        // Off the principal point the two differ: the nearer contour plane is steeper.
        let c0 = ImageLine::new([1.0, 0.0, -579.5]).unwrap();
        let c1 = ImageLine::new([1.0, 0.0, -619.5]).unwrap();
        let axis = axis_from_contours(&k(), &c0, &c1, [599.5, 0.0]).unwrap();
        let mid = middle_line(&c0, &c1, [599.5, 0.0]).unwrap();
        assert!(mid.distance_px(599.5, 0.0).abs() < 1e-9);
        let u_axis = -axis.abc[2] / axis.abc[0];
        assert!((u_axis - 599.5).abs() > 0.1, "{u_axis}");
    }

    #[test]
    fn bad_input_is_a_typed_error() {
        assert_eq!(ImageLine::new([f64::NAN, 0.0, 1.0]), Err(LineError::NotFinite));
        assert_eq!(ImageLine::new([0.0, 0.0, 1.0]), Err(LineError::Degenerate));
        let c = ImageLine::new([1.0, 0.0, -300.0]).unwrap();
        assert_eq!(axis_from_contours(&k(), &c, &c, [310.0, 0.0]), Err(LineError::NoAxis));
        assert_eq!(axis_from_contours(&k(), &c, &c, [300.0, 0.0]), Err(LineError::InteriorOnLine));
        let singular = Matrix3::zeros();
        let c1 = ImageLine::new([1.0, 0.0, -340.0]).unwrap();
        assert_eq!(axis_from_contours(&singular, &c, &c1, [320.0, 0.0]), Err(LineError::NoAxis));
    }
}
