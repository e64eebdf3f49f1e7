//! Helpers shared by the detector's integration tests (each test file includes this module
//! and uses what it needs).

use estimator::calib::Intrinsics;
use nalgebra::Vector2;
use vision::ours::{OursConfig, OursDetector};
use vision::synth::Cylinder;
use vision::{RgbView, ShaftDetection, ShaftDetector};

/// A shaft (radius 4 mm, 0.4 m long, camera frame, metres) whose distal end is at the
/// measured pixel `tip_px` at depth `z_m`, pointing away from the tip along the image
/// direction `angle_deg`, tilted in depth by `tilt_deg` (positive: farther away from the tip).
#[allow(dead_code, reason = "not every test file uses every helper")]
pub fn shaft(k: &Intrinsics, tip_px: [f64; 2], z_m: f64, angle_deg: f64, tilt_deg: f64) -> Cylinder {
    let p = k.undistort_px(&Vector2::new(tip_px[0], tip_px[1]));
    let (x, y) = ((p.x - k.cx) / k.fx * z_m, (p.y - k.cy) / k.fy * z_m);
    let (a, t) = (angle_deg.to_radians(), tilt_deg.to_radians());
    Cylinder {
        point_m: [x, y, z_m],
        direction: [a.cos() * t.cos(), a.sin() * t.cos(), t.sin()],
        radius_m: 0.004,
        extent_m: [0.0, 0.4],
        albedo: 0.8,
    }
}

/// Ours with `cfg` on one RGB image of `k`'s size.
#[allow(dead_code, reason = "not every test file uses every helper")]
pub fn run(k: &Intrinsics, cfg: OursConfig, img: &[u8]) -> Vec<ShaftDetection> {
    let mut det = OursDetector::new(*k, cfg).unwrap();
    det.detect(&RgbView::new(k.width as usize, k.height as usize, img).unwrap()).unwrap()
}

/// Angle (degrees) and offset (undistorted pixels, at the middle of the detected span) of a
/// detection against a true cylinder `c`.
#[allow(dead_code, reason = "not every test file uses every helper")]
pub fn errors(k: &Intrinsics, d: &ShaftDetection, c: &Cylinder) -> (f64, f64) {
    let truth = c.axis_line(k).unwrap();
    let (a, b) = (d.centreline.abc, truth.abc);
    let angle = (a[0] * b[1] - a[1] * b[0]).abs().asin().to_degrees();
    let m0 = k.undistort_px(&Vector2::new(d.ends_px[0][0], d.ends_px[0][1]));
    let m1 = k.undistort_px(&Vector2::new(d.ends_px[1][0], d.ends_px[1][1]));
    let mid = 0.5 * (m0 + m1);
    (angle, truth.distance_px(mid.x, mid.y).abs())
}
