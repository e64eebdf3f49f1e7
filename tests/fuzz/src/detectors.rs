//! The shaft detectors (`vision::paper::PaperDetector`, `vision::ours::OursDetector`) on
//! arbitrary small images: `Ok` (shafts with finite geometry and a confidence in `0..=1`) or a
//! typed error, never a panic.

use estimator::calib::Intrinsics;
use vision::ours::{OursConfig, OursDetector};
use vision::paper::PaperDetector;
use vision::{RgbView, ShaftDetection, ShaftDetector};

use crate::Bytes;

/// Largest side of the fuzzed images, pixels (small: thousands of executions a second).
pub const MAX_SIDE: usize = 64;

/// `data` as: width and height bytes (`1 + b % MAX_SIDE` each), a distortion byte (none, mild,
/// strong barrel), a byte whose bit 0 gives the image a size other than the camera's, then the
/// RGB pixels (cycled over the bytes given; black when none).
pub fn run(data: &[u8]) {
    let mut b = Bytes::new(data);
    let w = 1 + usize::from(b.u8()) % MAX_SIDE;
    let h = 1 + usize::from(b.u8()) % MAX_SIDE;
    let distortion = match b.u8() % 3 {
        0 => [0.0; 5],
        1 => [-0.1, 0.02, 0.001, -0.001, 0.0],
        _ => [-0.6, 0.4, 0.0, 0.0, -0.1],
    };
    let other_size = b.u8() & 1 == 1;
    let pixels = b.rest();
    let mut image = vec![0u8; w * h * 3];
    if !pixels.is_empty() {
        for (i, p) in image.iter_mut().enumerate() {
            *p = pixels[i % pixels.len()];
        }
    }
    let Ok(view) = RgbView::new(w, h, &image) else { panic!("a {w}x{h} view of {} bytes", image.len()) };
    let (cw, ch) = if other_size { (w as u32 + 1, h as u32) } else { (w as u32, h as u32) };
    let k = Intrinsics {
        fx: 0.9 * cw as f64 + 1.0,
        fy: 0.9 * cw as f64 + 1.0,
        cx: cw as f64 / 2.0,
        cy: ch as f64 / 2.0,
        skew: 0.0,
        width: cw,
        height: ch,
        distortion,
    };
    let mut paper = PaperDetector::new(k);
    check(paper.detect(&view), other_size);
    if let Ok(mut ours) = OursDetector::new(k, OursConfig::default()) {
        check(ours.detect(&view), other_size);
    }
}

fn check(result: Result<Vec<ShaftDetection>, vision::DetectError>, other_size: bool) {
    match result {
        Ok(found) => {
            assert!(!other_size, "an image of another size than the camera's was accepted");
            for d in found {
                assert!((0.0..=1.0).contains(&d.confidence), "confidence {}", d.confidence);
                assert!(d.ends_px.iter().flatten().all(|v| v.is_finite()), "ends {:?}", d.ends_px);
            }
        }
        Err(_) => assert!(other_size, "a typed error for an image of the camera's size"),
    }
}
