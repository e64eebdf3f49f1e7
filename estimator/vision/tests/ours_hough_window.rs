//! The Hough transform's normal window (`OursConfig::hough_normal_window_deg`) on synthetic
//! images (`vision::synth`): a short shaft in a corner of a noisy clear frame, far from the
//! image centre, is found only with the window (its edgels' scattered normals spread one vote
//! each over many distance bins), and noisy tissue alone still gives nothing.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use estimator::calib::Intrinsics;
use vision::ShaftDetection;
use vision::ours::OursConfig;
use vision::synth::{Cylinder, Scene, render};

mod common;
use common::{errors, run, shaft};

/// True when `d` is within 1° of `c`'s axis and its span's middle within 3 px of it.
fn matches(k: &Intrinsics, d: &ShaftDetection, c: &Cylinder) -> bool {
    let (angle, offset) = errors(k, d, c);
    angle < 1.0 && offset < 3.0
}

#[test]
fn a_short_shaft_in_a_noisy_corner_is_found_only_with_the_normal_window() {
    let k = vision::synth::endoscope_camera();
    let off = OursConfig { hough_normal_window_deg: 0, ..OursConfig::default() };
    let on = OursConfig { hough_normal_window_deg: 5, ..OursConfig::default() };
    // (sensor noise, depth of the tip, scene seed): the shaft runs from its tip near the top
    // left corner out through the left border.
    for (noise, z, seed) in
        [(8.0, 0.1, 301), (12.0, 0.1, 300), (12.0, 0.1, 301), (12.0, 0.14, 300), (16.0, 0.1, 300), (16.0, 0.14, 301)]
    {
        let c = shaft(&k, [90.0, 70.0], z, 150.0, 10.0);
        let img = render(&k, &Scene { shafts: vec![c], seed, vessels: true, folds: true, noise });
        let (without, with) = (run(&k, off, &img), run(&k, on, &img));
        assert!(
            !without.iter().any(|d| matches(&k, d, &c)),
            "noise {noise}, z {z}, seed {seed}: found without the window"
        );
        assert!(!with.is_empty(), "noise {noise}, z {z}, seed {seed}: not found with the window");
        for d in &with {
            assert!(matches(&k, d, &c), "noise {noise}, z {z}, seed {seed}: a wrong detection {d:?}");
        }
    }
}

#[test]
fn noisy_tissue_alone_gives_no_detection_with_the_normal_window() {
    let k = vision::synth::endoscope_camera();
    let on = OursConfig { hough_normal_window_deg: 5, ..OursConfig::default() };
    for seed in 300..306 {
        let img = render(&k, &Scene { shafts: vec![], seed, vessels: true, folds: true, noise: 16.0 });
        let found = run(&k, on, &img);
        assert!(found.is_empty(), "seed {seed}: {found:?}");
    }
}
