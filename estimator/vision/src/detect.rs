//! The contract every shaft detector meets: an 8-bit sRGB image in, the instrument shafts it
//! sees out (best first; none is the clean "no shaft" answer), each with its centreline,
//! its two contour lines, two points on the centreline for the calibration, and a
//! confidence.
//!
//! Pixels: the image as measured (with the lens distortion) is indexed by integer pixels
//! whose centres are `(0, 0)` … `(w − 1, h − 1)`; lines are given in **undistorted** (ideal
//! pinhole) pixels of the same camera, OpenCV's convention; `ends_px` are **measured**
//! (distorted) pixels, what `estimator::calib::Observation::line_px` takes.

use estimator::calib::Intrinsics;
use nalgebra::Vector2;

use crate::shaft::{ImageLine, LineError};

/// A borrowed 8-bit sRGB image, row-major, 3 bytes per pixel, no padding.
#[derive(Clone, Copy, Debug)]
pub struct RgbView<'a> {
    width: usize,
    height: usize,
    data: &'a [u8],
}

/// Why bytes are not an image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ImageError {
    /// Zero width or height.
    #[error("image size must be positive (got {width}x{height})")]
    Empty {
        /// Width, pixels.
        width: usize,
        /// Height, pixels.
        height: usize,
    },
    /// The byte count is not `3 · width · height`.
    #[error("{got} bytes for a {width}x{height} RGB image (expected {expected})")]
    Length {
        /// Width, pixels.
        width: usize,
        /// Height, pixels.
        height: usize,
        /// `3 · width · height`.
        expected: usize,
        /// Bytes given.
        got: usize,
    },
}

impl<'a> RgbView<'a> {
    /// A view of `data` as a `width × height` RGB8 image.
    pub fn new(width: usize, height: usize, data: &'a [u8]) -> Result<Self, ImageError> {
        if width == 0 || height == 0 {
            return Err(ImageError::Empty { width, height });
        }
        let expected = width.checked_mul(height).and_then(|n| n.checked_mul(3)).unwrap_or(usize::MAX);
        if data.len() != expected {
            return Err(ImageError::Length { width, height, expected, got: data.len() });
        }
        Ok(Self { width, height, data })
    }

    /// Width, pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height, pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The bytes, row-major RGB.
    pub fn data(&self) -> &'a [u8] {
        self.data
    }

    /// `[r, g, b]` of pixel `(x, y)` (`x < width`, `y < height`; panics otherwise, like
    /// slice indexing).
    pub fn pixel(&self, x: usize, y: usize) -> [u8; 3] {
        let i = 3 * (y * self.width + x);
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }
}

/// A line segment found in an image: its two end points, **measured** (distorted) pixels.
/// What a line-segment detector (EDLines, LSD) gives, before any pairing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    /// First end point `[u, v]`, pixels.
    pub a: [f64; 2],
    /// Second end point `[u, v]`, pixels.
    pub b: [f64; 2],
}

impl Segment {
    /// Length, pixels.
    pub fn length_px(&self) -> f64 {
        (self.b[0] - self.a[0]).hypot(self.b[1] - self.a[1])
    }
}

/// One instrument shaft in an image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShaftDetection {
    /// The centreline, undistorted pixels: the exact projected axis (ours) or the middle
    /// line of the two contours (the calibration paper's).
    pub centreline: ImageLine,
    /// The two contour (edge) lines of the shaft, undistorted pixels.
    pub contours: [ImageLine; 2],
    /// Two points on the centreline spanning the visible shaft, **measured** (distorted)
    /// pixels, in no particular order: `estimator::calib::Observation::line_px`.
    pub ends_px: [[f64; 2]; 2],
    /// How sure the detector is, `0..=1` (each detector documents what it means).
    pub confidence: f64,
}

/// Why a detector refused an image (not the same as finding no shaft, which is `Ok(vec![])`).
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum DetectError {
    /// The image's size is not the camera's.
    #[error("image is {width}x{height} but the camera's intrinsics are {camera_width}x{camera_height}")]
    SizeMismatch {
        /// Image width, pixels.
        width: usize,
        /// Image height, pixels.
        height: usize,
        /// Intrinsics width, pixels.
        camera_width: u32,
        /// Intrinsics height, pixels.
        camera_height: u32,
    },
}

/// A shaft detector. `detect` takes `&mut self` so that a detector can keep its working
/// buffers between frames (no allocation per frame once warm).
pub trait ShaftDetector {
    /// A short name for reports (`"paper"`, `"ours"`).
    fn name(&self) -> &'static str;
    /// The camera this detector was built for.
    fn intrinsics(&self) -> &Intrinsics;
    /// The shafts in `image`, best first; empty when there is none.
    fn detect(&mut self, image: &RgbView<'_>) -> Result<Vec<ShaftDetection>, DetectError>;
}

/// Checks that `image` has the camera's size.
pub fn check_size(k: &Intrinsics, image: &RgbView<'_>) -> Result<(), DetectError> {
    if image.width() != k.width as usize || image.height() != k.height as usize {
        return Err(DetectError::SizeMismatch {
            width: image.width(),
            height: image.height(),
            camera_width: k.width,
            camera_height: k.height,
        });
    }
    Ok(())
}

/// The line through two **measured** pixels, in undistorted pixels (both points undistorted
/// with `k`, then joined).
pub fn undistorted_line(k: &Intrinsics, a: [f64; 2], b: [f64; 2]) -> Result<ImageLine, LineError> {
    let p = k.undistort_px(&Vector2::new(a[0], a[1]));
    let q = k.undistort_px(&Vector2::new(b[0], b[1]));
    // l = p̃ × q̃
    ImageLine::new([p.y - q.y, q.x - p.x, p.x * q.y - q.x * p.y])
}

/// Luma (ITU-R BT.601, `0.299 R + 0.587 G + 0.114 B`, 0..=255) of every pixel into `out`
/// (resized to `width · height`), row-major.
pub fn luma_into(image: &RgbView<'_>, out: &mut Vec<f32>) {
    out.clear();
    out.extend(
        image
            .data()
            .chunks_exact(3)
            .map(|p| 0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2])),
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_refuse_wrong_sizes() {
        assert!(matches!(RgbView::new(0, 4, &[]), Err(ImageError::Empty { .. })));
        assert!(matches!(RgbView::new(2, 2, &[0; 11]), Err(ImageError::Length { expected: 12, got: 11, .. })));
        let v = RgbView::new(2, 2, &[1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12]).unwrap();
        assert_eq!(v.pixel(1, 1), [10, 11, 12]);
        let mut l = Vec::new();
        luma_into(&v, &mut l);
        assert_eq!(l.len(), 4);
        assert!((l[0] - (0.299 + 0.587 * 2.0 + 0.114 * 3.0)).abs() < 1e-4);
    }

    #[test]
    fn undistorted_line_without_distortion_is_the_join() {
        let k = Intrinsics {
            fx: 400.0,
            fy: 400.0,
            cx: 320.0,
            cy: 240.0,
            skew: 0.0,
            width: 640,
            height: 480,
            distortion: [0.0; 5],
        };
        let l = undistorted_line(&k, [10.0, 20.0], [110.0, 20.0]).unwrap();
        assert!(l.distance_px(50.0, 20.0).abs() < 1e-12);
        assert!((l.distance_px(50.0, 25.0).abs() - 5.0).abs() < 1e-12);
        let size = check_size(&k, &RgbView::new(2, 2, &[0; 12]).unwrap());
        assert!(matches!(size, Err(DetectError::SizeMismatch { .. })));
    }
}
