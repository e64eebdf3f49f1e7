//! The shaft's projected axis from its two contour lines (`vision::shaft`) against the
//! simulated endoscope's analytic ground truth: ours (the plane bisecting the two tangent
//! planes) is the true axis to rounding on every frame; the calibration paper's middle line of
//! the two image lines leaves it, by how much is printed and must be measurable.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a panic is a failed test")]

use sim::endoscope::config::RealismConfig;
use sim::endoscope::{DemoMotion, EndoscopeConfig, StereoRenderer};
use vision::shaft::{ImageLine, axis_from_contours, middle_line};

#[test]
fn the_exact_axis_matches_the_truth_and_the_middle_line_does_not() {
    let cfg = EndoscopeConfig { realism: RealismConfig::none(), ..Default::default() };
    let k = cfg.camera.intrinsics.k();
    let mut renderer = StereoRenderer::new(cfg.clone(), cfg.instrument.mesh().unwrap()).unwrap();
    // Two stretches of the demo motion, the second quick (the shaft sweeps the image).
    let motions = [DemoMotion { speed: 1.0, phase_s: 0.0 }, DemoMotion { speed: 4.0, phase_s: 3.0 }];
    let (mut checked, mut mid_err_px) = (0, Vec::new());
    for motion in &motions {
        for n in 0..40u64 {
            let t = 1_000_000_000 + n * 100_000_000;
            let frame = renderer.render(t, &|t| motion.state_at(t)).unwrap();
            for eye in &frame.truth {
                let Some(truth) = eye.instruments.first() else { continue };
                let (Some(contours), Some(axis)) = (&truth.contours, &truth.axis) else { continue };
                let Some([p, q]) = axis.segment_ideal_px else { continue };
                let interior = [(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0];
                let c0 = ImageLine::new(contours[0].line_ideal).unwrap();
                let c1 = ImageLine::new(contours[1].line_ideal).unwrap();
                let ours = axis_from_contours(&k, &c0, &c1, interior).unwrap();
                let want = ImageLine::new(axis.line_ideal).unwrap();
                let same = (0..3).all(|i| (ours.abc[i] - want.abc[i]).abs() < 1e-9)
                    || (0..3).all(|i| (ours.abc[i] + want.abc[i]).abs() < 1e-9);
                assert!(same, "frame {n}: ours {:?}, truth {:?}", ours.abc, want.abc);
                // Contour 0 on the positive side of ours, as documented.
                if let Some([a, b]) = contours[0].segment_ideal_px {
                    let m = [(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0];
                    assert!(ours.distance_px(m[0], m[1]) > 0.0, "frame {n}");
                    assert!(middle_line(&c0, &c1, interior).unwrap().distance_px(m[0], m[1]) > 0.0, "frame {n}");
                }
                // The paper's middle line: its distance from the true axis at the visible
                // segment's two ends.
                let mid = middle_line(&c0, &c1, interior).unwrap();
                let e = mid.distance_px(p[0], p[1]).abs().max(mid.distance_px(q[0], q[1]).abs());
                mid_err_px.push(e);
                checked += 1;
            }
        }
    }
    assert!(checked >= 60, "{checked} eye views with the shaft visible");
    mid_err_px.sort_by(f64::total_cmp);
    let median = mid_err_px[mid_err_px.len() / 2];
    let max = mid_err_px[mid_err_px.len() - 1];
    eprintln!("middle line vs the true axis over {checked} views: median {median:.3} px, max {max:.3} px");
    assert!(max > 0.1, "the middle line's perspective error should show: max {max} px");
}
