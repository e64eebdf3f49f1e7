//! Our shaft detector on synthetic images with exact ground truth (`vision::synth`): the
//! detected axis against the true projected axis, no detection on tissue alone, two crossing
//! shafts, bad input.

use estimator::calib::Intrinsics;
use nalgebra::Vector2;
use proptest::prelude::*;
use vision::ours::{OursConfig, OursConfigError, OursDetector};
use vision::synth::{Cylinder, Scene, render};
use vision::{DetectError, RgbView, ShaftDetection, ShaftDetector};

fn camera() -> Intrinsics {
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

/// A shaft whose distal end is at pixel `tip_px` (measured) at depth `z_m`, pointing away
/// from the tip along the image direction `angle_deg`, tilted in depth by `tilt_deg`
/// (positive: farther away from the tip).
fn shaft(k: &Intrinsics, tip_px: [f64; 2], z_m: f64, angle_deg: f64, tilt_deg: f64) -> Cylinder {
    let p = k.undistort_px(&Vector2::new(tip_px[0], tip_px[1]));
    let x = (p.x - k.cx) / k.fx * z_m;
    let y = (p.y - k.cy) / k.fy * z_m;
    let (a, t) = (angle_deg.to_radians(), tilt_deg.to_radians());
    Cylinder {
        point_m: [x, y, z_m],
        direction: [a.cos() * t.cos(), a.sin() * t.cos(), t.sin()],
        radius_m: 0.004,
        extent_m: [0.0, 0.4],
        albedo: 0.8,
    }
}

fn scene(shafts: Vec<Cylinder>, seed: u64) -> Scene {
    Scene { shafts, seed, vessels: true, folds: true, noise: 4.0 }
}

/// Angle (degrees) and offset (pixels, at the middle of the detected span) of a detection
/// against a true cylinder.
fn errors(k: &Intrinsics, d: &ShaftDetection, c: &Cylinder) -> (f64, f64) {
    let truth = c.axis_line(k).unwrap();
    let (a, b) = (d.centreline.abc, truth.abc);
    let angle = (a[0] * b[1] - a[1] * b[0]).abs().asin().to_degrees();
    let m0 = k.undistort_px(&Vector2::new(d.ends_px[0][0], d.ends_px[0][1]));
    let m1 = k.undistort_px(&Vector2::new(d.ends_px[1][0], d.ends_px[1][1]));
    let mid = 0.5 * (m0 + m1);
    (angle, truth.distance_px(mid.x, mid.y).abs())
}

fn detect(k: &Intrinsics, s: &Scene) -> Vec<ShaftDetection> {
    let img = render(k, s);
    let mut det = OursDetector::new(*k, OursConfig::default()).unwrap();
    det.detect(&RgbView::new(k.width as usize, k.height as usize, &img).unwrap()).unwrap()
}

#[test]
fn a_shaft_near_the_centre_at_30_to_150_mm_is_found_precisely() {
    let k = camera();
    for (i, &(z, angle, tilt)) in
        [(0.03, 20.0, 10.0), (0.06, 160.0, 30.0), (0.1, -35.0, 0.0), (0.15, 95.0, -20.0)].iter().enumerate()
    {
        let c = shaft(&k, [300.0, 250.0], z, angle, tilt);
        let found = detect(&k, &scene(vec![c], 10 + i as u64));
        if std::env::var_os("OURS_DUMP").is_some() {
            let img = render(&k, &scene(vec![c], 10 + i as u64));
            let mut f = b"P6\n640 480\n255\n".to_vec();
            f.extend_from_slice(&img);
            std::fs::write(format!("/tmp/ours_centre{i}.ppm"), f).unwrap();
        }
        assert!(!found.is_empty(), "z = {z}: not found");
        let (ang, off) = errors(&k, &found[0], &c);
        println!("centre z={z} angle={ang:.4}° offset={off:.3}px conf={:.2} n={}", found[0].confidence, found.len());
        assert!(ang < 0.1 && off < 0.3, "z = {z}: angle {ang}°, offset {off} px");
        assert!(found[0].confidence > 0.3);
    }
}

#[test]
fn a_shaft_near_the_border_is_found_precisely() {
    let k = camera();
    for (i, &(tip, z, angle, tilt)) in [
        ([200.0, 45.0], 0.05, 2.0, 0.0),
        ([590.0, 150.0], 0.08, 88.0, 15.0),
        ([420.0, 440.0], 0.12, 183.0, 20.0),
        ([95.0, 330.0], 0.04, -85.0, -10.0),
    ]
    .iter()
    .enumerate()
    {
        let c = shaft(&k, tip, z, angle, tilt);
        let found = detect(&k, &scene(vec![c], 20 + i as u64));
        if std::env::var_os("OURS_DUMP").is_some() {
            let img = render(&k, &scene(vec![c], 20 + i as u64));
            let mut f = b"P6\n640 480\n255\n".to_vec();
            f.extend_from_slice(&img);
            std::fs::write(format!("/tmp/ours_border{i}.ppm"), f).unwrap();
        }
        assert!(!found.is_empty(), "tip {tip:?}: not found");
        let (ang, off) = errors(&k, &found[0], &c);
        println!("border tip={tip:?} angle={ang:.4}° offset={off:.3}px n={}", found.len());
        assert!(ang < 0.1 && off < 0.3, "tip {tip:?}: angle {ang}°, offset {off} px");
    }
}

#[test]
fn tissue_alone_gives_no_detection() {
    let k = camera();
    for seed in 0..6 {
        let found = detect(&k, &scene(vec![], 100 + seed));
        assert!(found.is_empty(), "seed {seed}: {found:?}");
    }
}

#[test]
fn two_crossing_shafts_give_two_detections() {
    let k = camera();
    let a = shaft(&k, [250.0, 260.0], 0.07, 20.0, 10.0);
    let mut b = shaft(&k, [400.0, 220.0], 0.09, 150.0, 5.0);
    b.albedo = 0.35;
    let found = detect(&k, &scene(vec![a, b], 7));
    assert_eq!(found.len(), 2, "{found:?}");
    for c in [&a, &b] {
        let best = found.iter().map(|d| errors(&k, d, c)).min_by(|x, y| x.1.total_cmp(&y.1)).unwrap();
        println!("crossing angle={:.4}° offset={:.3}px", best.0, best.1);
        assert!(best.0 < 0.15 && best.1 < 0.5, "{best:?}");
    }
}

#[test]
fn bad_input_is_refused_or_empty() {
    let k = camera();
    let mut det = OursDetector::new(k, OursConfig::default()).unwrap();
    let small = vec![0u8; 3 * 32 * 24];
    assert!(matches!(
        det.detect(&RgbView::new(32, 24, &small).unwrap()),
        Err(DetectError::SizeMismatch { width: 32, .. })
    ));
    for v in [0u8, 128, 255] {
        let img = vec![v; 3 * 640 * 480];
        assert!(det.detect(&RgbView::new(640, 480, &img).unwrap()).unwrap().is_empty());
    }
    let bad = OursConfig { max_depth_m: 0.005, ..OursConfig::default() };
    assert!(matches!(OursDetector::new(k, bad), Err(OursConfigError::Invalid { field: "max_depth_m", .. })));
    let mut k_bad = k;
    k_bad.fx = f64::NAN;
    assert!(matches!(OursDetector::new(k_bad, OursConfig::default()), Err(OursConfigError::Intrinsics(_))));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    #[test]
    fn arbitrary_small_images_never_panic(
        w in 1usize..24,
        h in 1usize..24,
        bytes in proptest::collection::vec(any::<u8>(), 3 * 24 * 24),
        k1 in -0.3f64..0.1,
    ) {
        let k = Intrinsics {
            fx: 20.0,
            fy: 20.0,
            cx: w as f64 / 2.0,
            cy: h as f64 / 2.0,
            skew: 0.0,
            width: w as u32,
            height: h as u32,
            distortion: [k1, 0.0, 0.0, 0.0, 0.0],
        };
        let cfg = OursConfig { min_length_px: 4.0, ..OursConfig::default() };
        let mut det = OursDetector::new(k, cfg).unwrap();
        let img = RgbView::new(w, h, &bytes[..3 * w * h]).unwrap();
        let found = det.detect(&img).unwrap();
        for d in found {
            prop_assert!(d.confidence.is_finite());
        }
    }
}

#[test]
#[ignore = "debug: writes /tmp/ours_*.ppm"]
fn dump_images() {
    let k = camera();
    let cases = [
        ("z150", vec![shaft(&k, [300.0, 250.0], 0.15, 95.0, -20.0)]),
        ("border", vec![shaft(&k, [560.0, 80.0], 0.05, 10.0, 0.0)]),
        ("bg", vec![]),
    ];
    for (name, shafts) in cases {
        let img = render(&k, &scene(shafts, 11));
        let mut f = format!("P6\n640 480\n255\n").into_bytes();
        f.extend_from_slice(&img);
        std::fs::write(format!("/tmp/ours_{name}.ppm"), f).unwrap();
    }
}

#[test]
fn a_distortion_that_does_not_invert_is_a_typed_error_not_a_panic() {
    // Found by the `detectors` fuzz target (tests/fuzz/regressions/detectors/): a strong barrel
    // polynomial folds back before this small image's corners, the undistortion diverges and
    // the Hough accumulator was sized on an infinite radius (overflow, or an unbounded
    // allocation for a large finite one).
    let k = estimator::calib::Intrinsics {
        fx: 0.9 * 33.0 + 1.0,
        fy: 0.9 * 33.0 + 1.0,
        cx: 16.5,
        cy: 27.0,
        skew: 0.0,
        width: 33,
        height: 54,
        distortion: [-0.6, 0.4, 0.0, 0.0, -0.1],
    };
    match vision::ours::OursDetector::new(k, vision::ours::OursConfig::default()) {
        Err(vision::ours::OursConfigError::Undistortion { radius_px, limit_px }) => {
            assert!(!(radius_px <= limit_px), "{radius_px} {limit_px}");
        }
        other => panic!("{:?}", other.map(|_| ())),
    }
    // The same camera without distortion is accepted.
    let ok = vision::ours::OursDetector::new(
        estimator::calib::Intrinsics { distortion: [0.0; 5], ..k },
        vision::ours::OursConfig::default(),
    );
    assert!(ok.is_ok());
}
