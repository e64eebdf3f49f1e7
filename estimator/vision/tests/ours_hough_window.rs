//! The Hough transform's normal window (`OursConfig::hough_normal_window_deg`) on synthetic
//! images (`vision::synth`): a short shaft in a corner of a noisy clear frame, far from the
//! image centre, is found only with the window (its edgels' scattered normals spread one vote
//! each over many distance bins), noisy tissue alone still gives nothing, and a
//! motion-blurred shaft (the mean of three instants, as the simulator renders the exposure)
//! turns the window off (`OursConfig::hough_window_max_blurred`).
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use estimator::calib::Intrinsics;
use vision::ours::{OursConfig, OursDetector};
use vision::synth::{Cylinder, Scene, render};
use vision::{RgbView, ShaftDetection};

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

/// The mean of three renderings of a shaft whose tip moves by `d_px` across it and whose
/// direction turns by 0.8° between them (a rotation about a far trocar during the exposure),
/// the middle one at `tip_px`; and the still frame of the middle instant.
fn blurred_and_still(
    k: &Intrinsics,
    tip_px: [f64; 2],
    z: f64,
    angle_deg: f64,
    d_px: f64,
    seed: u64,
    noise: f64,
) -> (Vec<u8>, Vec<u8>) {
    let a = angle_deg.to_radians();
    let n = [-a.sin(), a.cos()];
    let scene = |c: Cylinder| Scene { shafts: vec![c], seed, vessels: true, folds: true, noise };
    let mut acc = vec![0.0f64; (k.width * k.height * 3) as usize];
    for s in [-1.0, 0.0, 1.0] {
        let c = shaft(k, [tip_px[0] + s * d_px * n[0], tip_px[1] + s * d_px * n[1]], z, angle_deg + 0.8 * s, 10.0);
        for (m, v) in acc.iter_mut().zip(render(k, &scene(c))) {
            *m += f64::from(v) / 3.0;
        }
    }
    let blurred = acc.iter().map(|v| v.round().clamp(0.0, 255.0) as u8).collect();
    (blurred, render(k, &scene(shaft(k, tip_px, z, angle_deg, 10.0))))
}

/// The centrelines ours returns with `cfg`, and the frame's silhouette measure.
fn centrelines(k: &Intrinsics, cfg: OursConfig, img: &[u8]) -> (Vec<[f64; 3]>, (usize, f32)) {
    let mut det = OursDetector::new(*k, cfg).unwrap();
    let (found, trace) = det.detect_traced(&RgbView::new(k.width as usize, k.height as usize, img).unwrap()).unwrap();
    (found.iter().map(|d| d.centreline.abc).collect(), trace.silhouette)
}

#[test]
fn a_motion_blurred_shaft_turns_the_normal_window_off() {
    let k = vision::synth::endoscope_camera();
    let off = OursConfig { hough_normal_window_deg: 0, ..OursConfig::default() };
    let gated = OursConfig { hough_normal_window_deg: 5, ..OursConfig::default() };
    let ungated = OursConfig { hough_window_max_blurred: 1.0, ..gated };
    let mut changed_ungated = 0;
    // (tip, depth, direction, motion across the shaft per instant, seed, noise)
    for (tip, z, angle, d, seed, noise) in [
        ([300.0, 240.0], 0.08, 30.0, 6.0, 300, 4.0),
        ([300.0, 240.0], 0.08, 30.0, 6.0, 301, 4.0),
        ([300.0, 240.0], 0.08, 30.0, 6.0, 302, 8.0),
        ([350.0, 260.0], 0.07, -60.0, 5.0, 300, 4.0),
        ([350.0, 260.0], 0.07, -60.0, 5.0, 301, 8.0),
        ([320.0, 240.0], 0.06, 60.0, 4.0, 301, 4.0),
    ] {
        let (blurred, still) = blurred_and_still(&k, tip, z, angle, d, seed, noise);
        let what = format!("tip {tip:?}, {d} px per instant, seed {seed}, noise {noise}");
        let (_, sil_still) = centrelines(&k, gated, &still);
        assert!(
            sil_still.0 >= 100 && f64::from(sil_still.1) <= gated.hough_window_max_blurred,
            "{what}: still {sil_still:?}"
        );
        let (without, sil) = centrelines(&k, off, &blurred);
        assert!(f64::from(sil.1) > gated.hough_window_max_blurred, "{what}: blurred {sil:?}");
        assert_eq!(centrelines(&k, gated, &blurred).0, without, "{what}: the window was on");
        changed_ungated += usize::from(centrelines(&k, ungated, &blurred).0 != without);
    }
    // Without the gate the window changes what is returned on these frames.
    assert!(changed_ungated >= 3, "only {changed_ungated} frames changed by the window without the gate");
}
