//! # vision: comanip's image mathematics
//!
//! Pure functions on image measurements, no I/O (the pixels arrive through `hw_io::ipc`'s
//! frame service; the processes are in `controller/`). A crate beside `estimator`, not a module
//! of it: image work needs `std` and image buffers, which `estimator` (no_std-capable,
//! allocation-free on the 1 kHz path) and fulcrumd must not carry (`docs/architecture.md`).
//!
//! - [`shaft`]: the instrument shaft's projected axis from its two contour lines: the exact
//!   axis of a cylinder under perspective, and the middle line the dual RCM-arm calibration
//!   paper (Wang et al., *Vision-based calibration of dual RCM-based robot arms in
//!   human-robot collaborative minimally invasive surgery*, IEEE RA-L 2017) takes instead.
//!
//! - [`detect`]: the contract every shaft detector meets ([`ShaftDetector`]): an sRGB image
//!   in, the shafts out, best first, or none.
//!
//! - [`ours`]: our shaft detector (colour edgels, undistorted lines, cylinder physics,
//!   sub-pixel contours, the exact perspective axis).
//!
//! - [`synth`]: synthetic test images (analytic cylinders over textured tissue, with lens
//!   distortion) with exact ground truth, for the detectors' tests and benches.
//!
//! Units: pixels of the undistorted (ideal pinhole) image, OpenCV's convention (the centre of
//! the top-left pixel is `(0, 0)`); camera frame: x right, y down, z forward.
#![warn(missing_docs)]

pub mod detect;
pub mod edlines;
pub mod ours;
pub mod paper;
pub mod shaft;
pub mod synth;

pub use detect::{DetectError, ImageError, RgbView, Segment, ShaftDetection, ShaftDetector};
