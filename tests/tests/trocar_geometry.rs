//! Geometry of the trocar detectors: exact recovery, invariance, degenerate windows, the
//! paper's false-positive trap, bad input. Both modes.

mod common;

use common::*;
use estimator::trocar::lsq::{NormalSums, SolveError};
use estimator::trocar::{Detector, DetectorConfig, DetectorMode, Estimate, LineSample, SampleError};
use nalgebra::{UnitQuaternion, Vector3};
use proptest::prelude::*;

fn detector(mode: DetectorMode) -> Detector {
    Detector::new(&DetectorConfig { mode, ..Default::default() }).unwrap()
}

fn assert_finite(e: &Estimate) {
    if let Some(f) = e.fulcrum_base_m {
        assert!(f.iter().all(|v| v.is_finite()));
    }
    if let Some(fit) = e.fit {
        assert!(fit.point_base_m.iter().all(|v| v.is_finite()));
        assert!(fit.residual_m.is_finite() && fit.conditioning.is_finite() && fit.std_m.is_finite());
    }
}

const MODES: [DetectorMode; 2] = [DetectorMode::Paper, DetectorMode::Fast];

#[test]
fn exact_fulcrum_from_noiseless_lines() {
    let f = Vector3::new(0.42, -0.05, 0.03);
    let mut sums = NormalSums::new();
    for k in 0..12 {
        let axis = cone_axis(0.1 + 0.02 * k as f64, 0.7 * k as f64);
        sums.add(&line_through(&f, &axis, 0.15 + 0.01 * k as f64));
    }
    let fit = sums.solve(1e-9).unwrap();
    assert!((fit.fulcrum_base_m - f).norm() < 1e-12, "{}", fit.fulcrum_base_m);
    // SSR comes from c − bᵀF (O(1) sums): cancellation leaves ~1e-16·c, i.e. rms ≲ 1e-8 m.
    assert!(fit.rms_m < 1e-7, "{}", fit.rms_m);

    // Both detectors find it, exactly, from a noiseless pivoting motion.
    let (lines, phases, _) = scripted(&[f], 1, 0.0, 6.0);
    assert!(phases.iter().all(|p| *p == Phase::Inside));
    for mode in MODES {
        let mut d = detector(mode);
        let mut last = None;
        for l in &lines {
            last = Some(d.step(l));
        }
        let e = last.unwrap();
        assert!(e.state.is_inside(), "{mode:?} did not detect the trocar");
        let err = (e.fulcrum_base_m.unwrap() - f).norm();
        assert!(err < 1e-9, "{mode:?}: fulcrum off by {err} m");
    }
}

#[test]
fn invariant_under_rigid_motion_of_the_base() {
    let f = Vector3::new(0.40, 0.02, 0.05);
    let (lines, _, _) = scripted(&[f, Vector3::new(0.5, -0.1, 0.0)], 4, 2.0, 6.0);
    let rot = UnitQuaternion::from_euler_angles(0.3, -0.8, 1.9);
    let trans = Vector3::new(-0.7, 1.2, 0.4);
    for mode in MODES {
        let (mut a, mut b) = (detector(mode), detector(mode));
        let mut changes = 0;
        let mut prev = false;
        for l in &lines {
            let ea = a.step(l);
            let eb = b.step(&moved(l, &rot, &trans));
            assert_eq!(ea.state, eb.state, "{mode:?}: state differs after a rigid motion");
            if let (Some(fa), Some(fb)) = (ea.fulcrum_base_m, eb.fulcrum_base_m) {
                assert!((rot * fa + trans - fb).norm() < 1e-7, "{mode:?}: fulcrum is not covariant");
            }
            if ea.state.is_inside() != prev {
                changes += 1;
                prev = ea.state.is_inside();
            }
        }
        assert!(changes >= 6, "{mode:?}: the sequence must exercise insertions and extractions ({changes})");
    }
}

#[test]
fn parallel_lines_are_never_a_trocar() {
    let axis = Vector3::new(0.1, 0.2, -1.0).normalize();
    let mut sums = NormalSums::new();
    for k in 0..50 {
        sums.add(&LineSample::new(Vector3::new(0.4 + 0.003 * k as f64, 0.001 * k as f64, 0.3), axis));
    }
    assert!(matches!(sums.solve(1e-9), Err(SolveError::IllConditioned { .. })));
    for mode in MODES {
        let mut d = detector(mode);
        for k in 0..20_000 {
            // A wrist sliding sideways with a fixed axis (slightly noisy): nearly parallel lines.
            let t = k as f64 * 0.001;
            let wobble = Vector3::new(1e-5 * (7.0 * t).sin(), 1e-5 * (5.0 * t).cos(), 0.0);
            let l = LineSample::new(
                Vector3::new(0.3 + 0.05 * (0.5 * t).sin(), 0.05 * (0.3 * t).cos(), 0.3),
                (axis + wobble).normalize(),
            );
            let e = d.step(&l);
            assert_finite(&e);
            assert!(!e.state.is_inside(), "{mode:?} declared a trocar from parallel lines at {t} s");
            assert!(e.fulcrum_base_m.is_none());
        }
    }
}

#[test]
fn nearly_parallel_lines_through_a_point_do_not_make_a_trocar_in_fast_mode() {
    // Lines that do pass through one point but span only 0.3 degrees: the residual is tiny,
    // yet the point is undetermined along the axis. The conditioning gate must refuse it.
    let f = Vector3::new(0.4, 0.0, 0.0);
    let mut d = detector(DetectorMode::Fast);
    for k in 0..20_000 {
        let t = k as f64 * 0.001;
        let axis = cone_axis(0.1 + 0.0026 * (2.0 * t).sin(), 1.0);
        // Move the wrist along the axis too so lines keep being included.
        let e = d.step(&line_through(&f, &axis, 0.2 + 0.05 * (1.5 * t).sin()));
        assert!(!e.state.is_inside(), "fast mode declared an undetermined trocar at {t} s");
    }
}

#[test]
fn rotation_about_the_wrist_is_not_a_trocar() {
    // The paper's false-positive case: outside the body, the surgeon turns the instrument
    // about the wrist centre P (the passive wrist), so every line passes through P.
    let p = Vector3::new(0.35, 0.05, 0.30);
    for mode in MODES {
        let mut d = detector(mode);
        let mut fits = 0;
        for k in 0..30_000 {
            let t = k as f64 * 0.001;
            let axis = cone_axis(0.1 + 0.3 * (0.5 - 0.5 * (1.1 * t).cos()), 0.9 * t);
            let e = d.step(&LineSample::new(p, axis));
            assert!(!e.state.is_inside(), "{mode:?} took the wrist for a trocar at {t} s");
            if let Some(fit) = e.fit {
                // The lines do intersect (at P): the detector must see it and refuse it.
                if (fit.point_base_m - p).norm() < 1e-3 {
                    fits += 1;
                }
            }
        }
        assert!(fits > 1000, "{mode:?}: the test must produce fits at the wrist ({fits})");
    }
}

#[test]
fn bad_samples_are_rejected_and_change_nothing() {
    let f = Vector3::new(0.42, -0.05, 0.03);
    let (lines, _, _) = scripted(&[f], 1, 0.0, 4.0);
    for mode in MODES {
        let mut d = detector(mode);
        let mut last = None;
        for l in &lines {
            last = Some(d.step(l));
        }
        let before = last.unwrap();
        assert!(before.state.is_inside());
        let bad = [
            (LineSample::new(Vector3::new(f64::NAN, 0.0, 0.0), Vector3::z()), SampleError::NonFiniteWrist),
            (LineSample::new(Vector3::zeros(), Vector3::new(0.0, f64::INFINITY, 0.0)), SampleError::NonFiniteAxis),
            (LineSample::new(Vector3::new(1e6, 0.0, 0.0), Vector3::z()), SampleError::WristOutOfRange),
            (LineSample::new(Vector3::zeros(), Vector3::new(0.0, 0.0, 0.5)), SampleError::AxisNotUnit),
            (LineSample::new(Vector3::zeros(), Vector3::zeros()), SampleError::AxisNotUnit),
        ];
        for (sample, err) in bad {
            let e = d.step(&sample);
            assert_eq!(e.rejected, Some(err), "{mode:?}");
            assert_eq!(e.state, before.state);
            assert_eq!(e.fulcrum_base_m, before.fulcrum_base_m);
            assert_finite(&e);
        }
        // A good sample afterwards is accepted again.
        assert_eq!(d.step(lines.last().unwrap()).rejected, None);
    }
}

#[test]
fn reset_returns_to_outside() {
    let (lines, _, _) = scripted(&[Vector3::new(0.4, 0.0, 0.0)], 1, 0.0, 4.0);
    for mode in MODES {
        let mut d = detector(mode);
        for l in &lines {
            d.step(l);
        }
        d.reset();
        let e = d.step(&lines[0]);
        assert!(!e.state.is_inside() && e.fulcrum_base_m.is_none(), "{mode:?}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Lines through a point, with enough angular spread, give back that point.
    #[test]
    fn ls_recovers_the_common_point(
        fx in -1.0..1.0f64, fy in -1.0..1.0f64, fz in -1.0..1.0f64,
        dirs in proptest::collection::vec((0.05..1.2f64, 0.0..6.3f64, -0.5..0.5f64), 3..40),
    ) {
        let f = Vector3::new(fx, fy, fz);
        let mut sums = NormalSums::new();
        for (tilt, az, depth) in &dirs {
            sums.add(&line_through(&f, &cone_axis(*tilt, *az), *depth));
        }
        match sums.solve(1e-6) {
            Ok(fit) => {
                prop_assert!((fit.fulcrum_base_m - f).norm() < 1e-6 * (1.0 + fit.std_per_unit_noise));
                prop_assert!(fit.rms_m < 1e-6);
            }
            Err(SolveError::IllConditioned { .. }) => {} // too little spread: refusing is right
            Err(e) => prop_assert!(false, "unexpected {e}"),
        }
    }

    /// Whatever finite lines come in, the solver returns a finite point or a typed refusal,
    /// and removing lines restores the sums.
    #[test]
    fn ls_is_total_and_removal_inverts_addition(
        raw in proptest::collection::vec(((-2.0..2.0f64, -2.0..2.0f64, -2.0..2.0f64), (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64)), 0..30),
    ) {
        let lines: Vec<LineSample> = raw.iter().filter_map(|((px, py, pz), (zx, zy, zz))| {
            let z = Vector3::new(*zx, *zy, *zz);
            (z.norm() > 1e-3).then(|| LineSample::new(Vector3::new(*px, *py, *pz), z.normalize()))
        }).collect();
        let mut sums = NormalSums::new();
        for l in &lines { sums.add(l); }
        if let Ok(fit) = sums.solve(1e-9) {
            prop_assert!(fit.fulcrum_base_m.iter().all(|v| v.is_finite()));
            prop_assert!(fit.ssr_m2.is_finite() && fit.ssr_m2 >= 0.0);
        }
        let half = lines.len() / 2;
        let mut expect = NormalSums::new();
        for l in &lines[..half] { expect.add(l); }
        for l in &lines[half..] { sums.remove(l); }
        let (a, b) = (sums.solve(1e-9), expect.solve(1e-9));
        match (a, b) {
            (Ok(x), Ok(y)) => prop_assert!((x.fulcrum_base_m - y.fulcrum_base_m).norm() < 1e-6 * (1.0 + y.std_per_unit_noise * y.std_per_unit_noise)),
            (Err(_), Err(_)) => {}
            (x, y) => {
                // Only near the gate may the two disagree.
                let c = x.map(|f| f.conditioning).or(y.map(|f| f.conditioning)).unwrap();
                prop_assert!(c < 1e-6, "removal changed the verdict far from the gate: {c}");
            }
        }
    }
}

/// Lines through `f` whose axes swing about one fixed axis only (a coplanar pencil): every
/// one-parameter motion has such a virtual pivot, so the fast mode must not call it a trocar;
/// the same point approached from a cone of directions is one.
#[test]
fn a_one_axis_swing_is_not_a_trocar_but_a_cone_through_the_same_point_is() {
    let f = Vector3::new(0.32, -0.02, 0.0);
    let run = |cone: bool| {
        let mut d = detector(DetectorMode::Fast);
        let mut inside = false;
        for i in 0..3000 {
            let t = i as f64 * 1e-3;
            let pitch = 0.2 * (2.0 * std::f64::consts::PI * 0.4 * t).sin();
            let yaw = if cone { 0.15 * (2.0 * std::f64::consts::PI * 0.3 * t).sin() } else { 0.0 };
            let axis = (UnitQuaternion::from_euler_angles(pitch, yaw, 0.0) * Vector3::new(0.0, 0.0, -1.0)).normalize();
            // The instrument slides through the point (±1 cm), as through a body wall.
            let depth = 0.20 + 0.01 * (2.0 * std::f64::consts::PI * 0.25 * t).sin();
            let e = d.step(&line_through(&f, &axis, depth));
            inside |= e.state.is_inside();
        }
        inside
    };
    assert!(!run(false), "a coplanar pencil of lines was taken for a trocar");
    assert!(run(true), "lines through one point from a cone of directions were not detected");
}

/// Outside, sliding the instrument along its own axis (entering a port) starts a new segment:
/// the lines of the approach before it no longer take part in the fit.
#[test]
fn an_axial_slide_restarts_the_segment_outside() {
    let mut d = detector(DetectorMode::Fast);
    // A wandering free motion: lines through no common point.
    for i in 0..400 {
        let t = i as f64 * 1e-3;
        let axis = cone_axis(0.3 + 0.2 * t, 2.0 * t);
        let wrist = Vector3::new(0.3 + 0.1 * t, 0.05 * t, 0.3);
        d.step(&LineSample::new(wrist, axis));
    }
    let axis = cone_axis(0.38, 0.8);
    let start = Vector3::new(0.34, 0.02, 0.3);
    let before = d.step(&LineSample::new(start, axis));
    assert!(before.window_fill > 1, "the free motion should have built a segment");
    // Slide 3 cm along the axis, 0.1 mm per sample: no lateral motion, no rotation.
    let mut e = before;
    for k in 1..=300 {
        e = d.step(&LineSample::new(start + axis * (k as f64 * 1e-4), axis));
    }
    assert_eq!(e.window_fill, 1, "the slide should have restarted the segment");
    assert!(!e.state.is_inside());
}

/// Inside a trocar whose lines are quiet, the extraction gate adapts down from
/// `extract_gate_m` (8 mm) towards `extract_gate_min_m`: a line 4 mm off the fulcrum ends
/// the insertion, where the fixed 8 mm gate would not.
#[test]
fn the_adaptive_extraction_gate_sees_a_small_departure() {
    let f = Vector3::new(0.3, 0.0, 0.0);
    let run = |adaptive: bool| {
        let mut cfg = DetectorConfig { mode: DetectorMode::Fast, ..Default::default() };
        if !adaptive {
            cfg.fast.extract_gate_min_m = cfg.fast.extract_gate_m;
        }
        let mut d = Detector::new(&cfg).unwrap();
        let mut inside_at = None;
        for i in 0..8000 {
            let t = i as f64 * 1e-3;
            let axis = cone_axis(0.2 + 0.1 * (1.3 * t).sin(), 1.7 * t);
            // From 7 s on, the line passes 4 mm beside the fulcrum (the instrument has left).
            let offset = if t >= 7.0 { axis.cross(&Vector3::x()).normalize() * 0.004 } else { Vector3::zeros() };
            // The instrument slides in and out of the trocar (±1 cm), as in any manipulation.
            let depth = 0.2 + 0.01 * (0.9 * t).sin();
            let e = d.step(&line_through(&(f + offset), &axis, depth));
            if t < 7.0 && e.state.is_inside() && inside_at.is_none() {
                inside_at = Some(t);
            }
            if t >= 7.0 && !e.state.is_inside() {
                return (inside_at, Some(t - 7.0));
            }
        }
        (inside_at, None)
    };
    let (inside, out) = run(true);
    assert!(inside.is_some(), "the trocar was not detected");
    let out = out.expect("the adaptive gate did not see the 4 mm departure");
    assert!(out < 0.05, "extraction took {out} s");
    let (_, fixed) = run(false);
    assert!(fixed.is_none(), "the fixed 8 mm gate should not see a 4 mm departure");
}

/// Exponential forgetting: scaling every line's weight changes no solution; new lines then
/// dominate old ones.
#[test]
fn forgetting_sums_keep_the_solution_and_let_new_lines_dominate() {
    let a = Vector3::new(0.3, 0.0, 0.0);
    let b = Vector3::new(0.3, 0.01, 0.0);
    let mut sums = NormalSums::new();
    for k in 0..10 {
        sums.add(&line_through(&a, &cone_axis(0.1 + 0.02 * k as f64, 0.9 * k as f64), 0.2));
    }
    let before = sums.solve(1e-9).unwrap();
    sums.decay(0.5);
    let after = sums.solve(1e-9).unwrap();
    assert!((before.fulcrum_base_m - after.fulcrum_base_m).norm() < 1e-12);
    assert!((after.weight - 5.0).abs() < 1e-12, "{}", after.weight);
    for k in 0..400 {
        sums.decay(0.99);
        sums.add(&line_through(&b, &cone_axis(0.1 + 0.001 * k as f64, 0.05 * k as f64), 0.2));
    }
    let f = sums.solve(1e-9).unwrap().fulcrum_base_m;
    assert!((f - b).norm() < 1e-4, "forgotten lines still pull the point: {} mm off", (f - b).norm() * 1e3);
}
