//! The selection of observations (a line is kept only when the tool tip is in view): box
//! probabilities, the likelihood's gradient, the bound of the kept lines, and our pipeline's
//! selection-aware stage against the guard alone (simulated data from `sim`).

use estimator::calib::crb::{CrbError, cramer_rao_bound, first_order_bound, selected_bound};
use estimator::calib::ours::{OursConfig, solve_ours_prepared};
use estimator::calib::prepare::prepare;
use estimator::calib::selection::{
    SelectionConfig, SelectionError, box_probability, box_probability_gradient, normal_mass, selection_likelihood,
    standard_bivariate_box,
};
use estimator::calib::{KinematicNoise, pose_errors};
use nalgebra::{Isometry3, Matrix2, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use sim::calib::{CalibGeometry, CalibProtocol, NoiseUnits, ecm_grid, generate_calibration, psm_grid};

fn protocol(geometry: CalibGeometry, sigma: f64, seed: u64) -> CalibProtocol {
    CalibProtocol { geometry, n_e: 3, n_t: 3, sigma, units: NoiseUnits::Metre, pixel_sigma_px: 0.0, seed }
}

#[test]
fn box_probability_matches_closed_forms_and_sampling() {
    // Independent coordinates: the product of the two one-dimensional masses.
    let s = Matrix2::new(4.0, 0.0, 0.0, 9.0);
    let (lo, hi) = (Vector2::new(-1.0, -7.0), Vector2::new(3.0, 2.0));
    let want = normal_mass(-0.5, 1.5) * normal_mass(-7.0 / 3.0, 2.0 / 3.0);
    assert!((box_probability(&s, &lo, &hi) - want).abs() < 1e-9, "{} vs {want}", box_probability(&s, &lo, &hi));
    // A box that holds everything, one that holds nothing, and a half-plane.
    assert!((box_probability(&s, &Vector2::repeat(-100.0), &Vector2::repeat(100.0)) - 1.0).abs() < 1e-9);
    assert_eq!(box_probability(&s, &Vector2::new(50.0, 0.0), &Vector2::new(60.0, 1.0)), 0.0);
    // Strongly correlated (ρ = 0.95): against 400 000 draws (standard error ≈ 8e-4).
    let s = Matrix2::new(900.0, 0.95 * 30.0 * 40.0, 0.95 * 30.0 * 40.0, 1600.0);
    let (lo, hi) = (Vector2::new(-10.0, -50.0), Vector2::new(45.0, 20.0));
    let l = s.cholesky().unwrap().l();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let n = 400_000;
    let inside = (0..n)
        .filter(|_| {
            let z = Vector2::new(rng.sample(rand_distr::StandardNormal), rng.sample(rand_distr::StandardNormal));
            let x = l * z;
            (0..2).all(|k| lo[k] <= x[k] && x[k] <= hi[k])
        })
        .count();
    let mc = inside as f64 / n as f64;
    let p = box_probability(&s, &lo, &hi);
    assert!((p - mc).abs() < 4e-3, "quadrature {p} vs sampling {mc}");
}

/// `P(x ∈ [lo, hi])`, `x ~ N(0, s)`, by a 200 000-interval Simpson rule over the first
/// coordinate (±9 standard deviations) of the second's conditional mass: the reference.
fn box_probability_by_simpson(s: &Matrix2<f64>, lo: &Vector2<f64>, hi: &Vector2<f64>) -> f64 {
    let (sd1, rho_sd) = (s[(0, 0)].sqrt(), s[(0, 1)] / s[(0, 0)]);
    let cond_sd = (s[(1, 1)] - s[(0, 1)] * s[(0, 1)] / s[(0, 0)]).sqrt();
    let (a, b) = ((lo[0] / sd1).max(-9.0), (hi[0] / sd1).min(9.0));
    let n = 200_000;
    let h = (b - a) / n as f64;
    let f = |w: f64| {
        let x1 = w * sd1;
        let m = rho_sd * x1;
        (-0.5 * w * w).exp() / (2.0 * std::f64::consts::PI).sqrt()
            * normal_mass(((lo[1] - m) / cond_sd).max(-40.0), ((hi[1] - m) / cond_sd).min(40.0))
    };
    let inner: f64 = (1..n).map(|i| f(a + i as f64 * h) * if i % 2 == 1 { 4.0 } else { 2.0 }).sum();
    h / 3.0 * (f(a) + inner + f(b))
}

#[test]
fn box_probability_short_cuts_and_quadrature_match_a_fine_simpson_rule() {
    // Tip covariances as the stage meets them (tens of pixels, correlated) and image-sized
    // boxes: one coordinate far inside its faces given the other (either way round, including
    // a tip far outside in the other coordinate, P small), near a corner, near one face.
    let s = Matrix2::new(2500.0, 0.6 * 50.0 * 20.0, 0.6 * 50.0 * 20.0, 400.0);
    let cases = [
        (Vector2::new(-60.0, -300.0), Vector2::new(500.0, 300.0)), // 2nd far given any 1st in range
        (Vector2::new(60.0, -300.0), Vector2::new(900.0, 300.0)),  // 1st 1.2σ / 3σ outside, P small
        (Vector2::new(-400.0, -25.0), Vector2::new(400.0, 600.0)), // 1st far given any 2nd
        (Vector2::new(-30.0, -15.0), Vector2::new(600.0, 500.0)),  // a corner
        (Vector2::new(-500.0, -500.0), Vector2::new(500.0, 500.0)), // everything
        // Faces about 4 conditional standard deviations away: too near for the short cuts.
        (Vector2::new(-60.0, -150.0), Vector2::new(500.0, 150.0)),
        (Vector2::new(-400.0, -25.0), Vector2::new(370.0, 600.0)),
    ];
    for (lo, hi) in cases {
        let (p, want) = (box_probability(&s, &lo, &hi), box_probability_by_simpson(&s, &lo, &hi));
        assert!(((p - want) / want).abs() < 3e-7, "box {lo:?}..{hi:?}: {p} vs Simpson {want}");
    }
    let sneg = Matrix2::new(400.0, -0.9 * 20.0 * 60.0, -0.9 * 20.0 * 60.0, 3600.0);
    for (lo, hi) in cases {
        let (p, want) = (box_probability(&sneg, &lo, &hi), box_probability_by_simpson(&sneg, &lo, &hi));
        assert!(((p - want) / want).abs() < 3e-7, "box {lo:?}..{hi:?}: {p} vs Simpson {want}");
    }
}

#[test]
fn standard_bivariate_box_matches_a_fine_simpson_rule() {
    // Genz's algorithm (both of its branches, |r| below and above 0.925, either sign) against
    // the Simpson reference, over boxes inside, across and in the tails of the distribution.
    let rs = [0.0, 0.1, -0.29, 0.31, -0.6, 0.74, 0.8, -0.9, 0.93, -0.95, 0.99, -0.999];
    let boxes = [
        (-1.0, 2.0, -0.5, 3.0),
        (-6.5, 6.5, -9.0, 9.0),
        (2.0, 5.0, 1.5, 7.0),
        (-5.0, -2.5, -2.6, -1.6),
        (-0.3, 0.4, 3.0, 8.0),
        (-7.0, -3.7, -1.3, 4.9),
        (0.7, 2.1, -6.6, -6.4),
        (-2.2, 4.3, 4.4, 10.0),
    ];
    let mut checked = 0;
    for &r in &rs {
        for &(a1, b1, a2, b2) in &boxes {
            let s = Matrix2::new(1.0, r, r, 1.0);
            let want = box_probability_by_simpson(&s, &Vector2::new(a1, a2), &Vector2::new(b1, b2));
            let p = standard_bivariate_box(a1, b1, a2, b2, r);
            let ok = if want > 1e-10 { ((p - want) / want).abs() < 3e-7 } else { (p - want).abs() < 1e-17 };
            assert!(ok, "r {r}, box [{a1}, {b1}] × [{a2}, {b2}]: {p} vs Simpson {want}");
            checked += 1;
        }
    }
    assert_eq!(checked, rs.len() * boxes.len());
    // Empty intervals hold nothing.
    assert_eq!(standard_bivariate_box(1.0, 1.0, -1.0, 1.0, 0.5), 0.0);
}

#[test]
fn box_probability_gradient_matches_differences() {
    let s = Matrix2::new(900.0, -700.0, -700.0, 1600.0);
    let (lo, hi) = (Vector2::new(-10.0, -50.0), Vector2::new(45.0, 20.0));
    let g = box_probability_gradient(&s, &lo, &hi);
    for k in 0..2 {
        let mut c = Vector2::zeros();
        c[k] = 1e-4;
        // P(x + c ∈ [lo, hi]) = P(x ∈ [lo − c, hi − c]).
        let num = (box_probability(&s, &(lo - c), &(hi - c)) - box_probability(&s, &(lo + c), &(hi + c))) / 2e-4;
        assert!((num - g[k]).abs() < 1e-6 + 1e-4 * num.abs(), "axis {k}: {num} vs {}", g[k]);
    }
}

#[test]
fn selection_likelihood_gradient_matches_differences() {
    let d = generate_calibration(&protocol(CalibGeometry::default(), 0.01, 11)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let noise = d.noise.unwrap();
    let cfg = SelectionConfig::default();
    // Away from the truth, so that every term has a slope.
    let at = Isometry3::from_parts(
        Translation3::from(d.truth.translation.vector + Vector3::new(0.004, -0.003, 0.002)),
        UnitQuaternion::from_scaled_axis(Vector3::new(0.01, -0.005, 0.008)) * d.truth.rotation,
    );
    let (_, g) = selection_likelihood(&set, &noise, &cfg, &at, &at).unwrap();
    for k in 0..6 {
        let h = 1e-5;
        let mut dv = Vector6::zeros();
        dv[k] = h;
        let moved = |s: f64| {
            let t = at.translation.vector + dv.fixed_rows::<3>(0) * s;
            let r = Rotation3::new(dv.fixed_rows::<3>(3) * s) * at.rotation.to_rotation_matrix();
            Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_rotation_matrix(&r))
        };
        let f = |s: f64| selection_likelihood(&set, &noise, &cfg, &at, &moved(s)).unwrap().0;
        let num = (f(1.0) - f(-1.0)) / (2.0 * h);
        assert!((num - g[k]).abs() < 1e-4 * (1.0 + num.abs()), "parameter {k}: numeric {num} analytic {}", g[k]);
    }
}

fn grid(g: &CalibGeometry) -> Vec<([f64; 4], [f64; 3])> {
    ecm_grid(g, 3).iter().flat_map(|e| psm_grid(g, 3).into_iter().map(move |p| (*e, p))).collect()
}

#[test]
fn the_selected_bound_is_the_naive_one_when_nothing_is_cut_and_is_repeatable() {
    let noise = KinematicNoise { rot_rad: 0.01, trans_m: 0.01, pixel_px: 0.0 };
    // A sensor 10× larger at the same focal length: no tip leaves the view.
    let mut big = CalibGeometry::default();
    big.intrinsics.width *= 10;
    big.intrinsics.height *= 10;
    big.intrinsics.cx = (big.intrinsics.width as f64 - 1.0) / 2.0;
    big.intrinsics.cy = (big.intrinsics.height as f64 - 1.0) / 2.0;
    let clean = generate_calibration(&protocol(big, 0.0, 0)).unwrap();
    let b = selected_bound(&clean.setup, &grid(&big), &clean.truth, &noise, 128, 1).unwrap();
    let naive = cramer_rao_bound(&clean.setup, &clean.observations, &clean.truth, &noise).unwrap();
    assert!((b.expected_kept - clean.observations.len() as f64).abs() < 1.0, "{}", b.expected_kept);
    for (x, y) in [
        (b.bound.translation_rms_m, naive.translation_rms_m),
        (b.bound.rotation_rms_rad, naive.rotation_rms_rad),
        (b.unselected.translation_rms_m, naive.translation_rms_m),
    ] {
        assert!((x / y - 1.0).abs() < 0.05, "selected {x} vs naive {y}");
    }
    // The protocol's camera cuts: fewer kept, a larger bound than the uncut grid; same seed,
    // same bound; another seed within a few per cent.
    let g = CalibGeometry::default();
    let clean = generate_calibration(&protocol(g, 0.0, 0)).unwrap();
    let a = selected_bound(&clean.setup, &grid(&g), &clean.truth, &noise, 128, 1).unwrap();
    let a2 = selected_bound(&clean.setup, &grid(&g), &clean.truth, &noise, 128, 1).unwrap();
    let a3 = selected_bound(&clean.setup, &grid(&g), &clean.truth, &noise, 128, 2).unwrap();
    assert!(a.expected_kept < 0.75 * grid(&g).len() as f64);
    assert!(a.bound.translation_rms_m > 1.2 * a.unselected.translation_rms_m);
    assert_eq!(a.bound.translation_rms_m, a2.bound.translation_rms_m);
    assert!((a3.bound.translation_rms_m / a.bound.translation_rms_m - 1.0).abs() < 0.05);
}

#[test]
fn the_first_order_bound_leaves_out_the_near_camera_tips_and_only_grows() {
    let noise = KinematicNoise { rot_rad: 0.01, trans_m: 0.01, pixel_px: 0.0 };
    let clean = generate_calibration(&protocol(CalibGeometry::default(), 0.0, 0)).unwrap();
    let b = |ratio: f64| first_order_bound(&clean.setup, &clean.observations, &clean.truth, &noise, ratio);
    // No limit: the naive bound itself.
    let all = b(f64::INFINITY).unwrap();
    let naive = cramer_rao_bound(&clean.setup, &clean.observations, &clean.truth, &noise).unwrap();
    assert_eq!(all.excluded, 0);
    assert!((all.bound.translation_rms_m / naive.translation_rms_m - 1.0).abs() < 1e-12);
    // Tighter limits leave out more observations (the near-camera ones exist at 10 mm per
    // frame) and the bound never shrinks.
    let mut last = all;
    for ratio in [0.5, 0.3, 0.2, 0.15] {
        let x = b(ratio).unwrap();
        assert!(x.excluded >= last.excluded, "{ratio}: {} < {}", x.excluded, last.excluded);
        assert!(x.bound.translation_rms_m >= last.bound.translation_rms_m * (1.0 - 1e-12));
        assert!(x.bound.rotation_rms_rad >= last.bound.rotation_rms_rad * (1.0 - 1e-12));
        last = x;
    }
    let at_default = b(SelectionConfig::default().depth_ratio).unwrap();
    assert!(at_default.excluded > 0 && at_default.excluded < clean.observations.len() / 5, "{}", at_default.excluded);
    assert!(at_default.bound.translation_rms_m > naive.translation_rms_m);
    // Nothing left: the pose is unobservable, a typed error.
    assert_eq!(b(0.0).unwrap_err(), CrbError::Singular);
    let bad = KinematicNoise { rot_rad: f64::NAN, ..noise };
    assert_eq!(
        first_order_bound(&clean.setup, &clean.observations, &clean.truth, &bad, 0.3).unwrap_err(),
        CrbError::NoiseModel
    );
}

#[test]
fn the_selection_aware_stage_removes_most_of_the_bias_the_guard_leaves() {
    // Metre reading at σ = 0.01, the lines alone: the guard leaves ours at about twice the
    // bound (docs/calibration.md); the selection-aware stage recovers most of the gap. (With
    // the shaft-position terms the guarded fit has no such gap left: docs/calibration.md.)
    let (mut with, mut without) = (0.0, 0.0);
    let lines = |d: &sim::calib::CalibDataset, selection: Option<SelectionConfig>| OursConfig {
        noise: d.noise,
        shaft_position: false,
        selection,
        ..OursConfig::default()
    };
    for seed in 200..208 {
        let d = generate_calibration(&protocol(CalibGeometry::default(), 0.01, seed)).unwrap();
        let set = prepare(&d.setup, &d.observations).unwrap();
        let on = solve_ours_prepared(&set, &lines(&d, Some(SelectionConfig::default()))).unwrap();
        let off = solve_ours_prepared(&set, &lines(&d, None)).unwrap();
        let s = on.selection.expect("the stage ran");
        assert_eq!(s.selected + s.plain + s.left_out, d.observations.len());
        assert!(s.selected > d.observations.len() / 2, "{s:?}");
        assert!(off.selection.is_none());
        with += pose_errors(&on.pose, &d.truth).translation_m.powi(2);
        without += pose_errors(&off.pose, &d.truth).translation_m.powi(2);
    }
    let ratio = (with / without).sqrt();
    assert!(ratio < 0.8, "RMS translation error with / without the stage = {ratio}");
}

#[test]
fn a_stage_that_runs_away_is_refused_and_the_guarded_fit_kept() {
    // The lines alone (with the shaft-position terms the stage barely moves on these data).
    let d = generate_calibration(&protocol(CalibGeometry::default(), 0.01, 204)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let lines = OursConfig { noise: d.noise, shaft_position: false, ..OursConfig::default() };
    let guarded = solve_ours_prepared(&set, &OursConfig { selection: None, ..lines }).unwrap();
    // A false-refusal probability so close to 1 that the limit is ~0: no real move passes.
    // The test alone decides (not the likelihood: the stage is far more likely here).
    let strict = SelectionConfig {
        false_refusal_probability: 1.0 - 1e-12,
        more_likely_overrides_test: false,
        ..SelectionConfig::default()
    };
    let o = solve_ours_prepared(&set, &OursConfig { selection: Some(strict), ..lines }).unwrap();
    assert!(o.selection.is_none());
    assert!(
        matches!(o.selection_refused, Some(SelectionError::RanAway { statistic, limit, dof, .. }) if dof > 0 && statistic > limit),
        "{:?}",
        o.selection_refused
    );
    assert_eq!(o.pose, guarded.pose);
    // With the default limit the same data are fitted with their selection.
    let o = solve_ours_prepared(&set, &lines).unwrap();
    assert!(o.selection_refused.is_none() && o.selection.is_some());
    // The strict limit, the likelihood deciding: the stage's pose is far more likely, taken.
    let strict = SelectionConfig { more_likely_overrides_test: true, ..strict };
    let o = solve_ours_prepared(&set, &OursConfig { selection: Some(strict), ..lines }).unwrap();
    assert!(o.selection.is_some_and(|s| s.accepted_on_likelihood), "{:?}", o.selection_refused);
}

#[test]
fn a_refused_move_to_a_far_more_likely_pose_is_taken() {
    use sim::calib::random_geometry;
    // Tuning geometry 9000, metre reading, σ = 0.01, trial seed 1001: the guarded fit is 8.5°
    // off (47 of its standard deviations from the truth); the stage moves 27 deviations, to
    // 0.8°, and fails the Hausman test. The likelihood says which of the two is wrong. (That
    // guarded fit is the candidates' comparison without the likelihood descent of the ones the
    // refinement left unexplained; with it, the guarded fit is 1.1° off and the stage passes.)
    let g = random_geometry(9000, false).unwrap();
    let d = generate_calibration(&protocol(g.geometry, 0.01, 1001)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let test_alone = SelectionConfig { more_likely_overrides_test: false, ..SelectionConfig::default() };
    let cfg = OursConfig { noise: d.noise, likelihood_descent: false, ..OursConfig::default() };
    let with_descent = solve_ours_prepared(&set, &OursConfig { likelihood_descent: true, ..cfg }).unwrap();
    assert!(with_descent.selection.is_some_and(|s| !s.accepted_on_likelihood), "{:?}", with_descent.selection_refused);
    assert!(pose_errors(&with_descent.pose, &d.truth).rotation_rad.to_degrees() < 1.5);
    let refused = solve_ours_prepared(&set, &OursConfig { selection: Some(test_alone), ..cfg }).unwrap();
    assert!(matches!(refused.selection_refused, Some(SelectionError::RanAway { .. })), "{:?}", refused.selection);
    assert!(pose_errors(&refused.pose, &d.truth).rotation_rad.to_degrees() > 3.0);
    let o = solve_ours_prepared(&set, &cfg).unwrap();
    assert!(o.selection.is_some_and(|s| s.accepted_on_likelihood), "{:?}", o.selection_refused);
    let e = pose_errors(&o.pose, &d.truth);
    assert!(e.rotation_rad.to_degrees() < 1.5 && e.translation_m < 0.015, "{e:?}");
}

#[test]
fn the_measured_move_test_passes_consistent_stages_and_refuses_a_run_away() {
    use sim::calib::random_geometry;
    let measured = SelectionConfig { influence_move_test: true, ..SelectionConfig::default() };
    // Consistent data (the default scene, σ = 0.01): the stage is taken, its move judged by
    // its measured covariance.
    for seed in 200..204 {
        let d = generate_calibration(&protocol(CalibGeometry::default(), 0.01, seed)).unwrap();
        let set = prepare(&d.setup, &d.observations).unwrap();
        let cfg = OursConfig { noise: d.noise, selection: Some(measured), ..OursConfig::default() };
        let o = solve_ours_prepared(&set, &cfg).unwrap();
        assert!(
            o.selection.is_some_and(|s| !s.accepted_on_likelihood && s.move_test_measured),
            "seed {seed}: {:?} {:?}",
            o.selection,
            o.selection_refused
        );
        // With the option off the efficiency-based test judges the same stage.
        let efficiency = SelectionConfig { influence_move_test: false, ..measured };
        let o = solve_ours_prepared(
            &set,
            &OursConfig { noise: d.noise, selection: Some(efficiency), ..OursConfig::default() },
        )
        .unwrap();
        assert!(o.selection.is_some_and(|s| !s.move_test_measured), "seed {seed}: {:?}", o.selection);
    }
    // Fewer observations than the measured covariance needs (`MIN_INFLUENCES`): the
    // efficiency-based test judges the stage, which is taken as without the option.
    let d = generate_calibration(&protocol(CalibGeometry::default(), 0.01, 200)).unwrap();
    let few = &d.observations[..estimator::calib::hausman::MIN_INFLUENCES - 5];
    let set = prepare(&d.setup, few).unwrap();
    let with =
        solve_ours_prepared(&set, &OursConfig { noise: d.noise, selection: Some(measured), ..OursConfig::default() });
    let efficiency = SelectionConfig { influence_move_test: false, ..measured };
    let without =
        solve_ours_prepared(&set, &OursConfig { noise: d.noise, selection: Some(efficiency), ..OursConfig::default() });
    let (with, without) = (with.unwrap(), without.unwrap());
    assert!(with.selection.is_some_and(|s| !s.move_test_measured), "{:?} {:?}", with.selection, with.selection_refused);
    assert_eq!(with.pose, without.pose);
    // Tuning geometry 9000, metres, σ = 0.01, trial 1001: the stage moves from a guarded fit
    // 8.5° off by 27 of its standard deviations. That guarded fit stopped after its last
    // re-whitening short of the objective the measured test rebuilds (one Newton step of that
    // objective is 7.9 of its standard deviations): the influences are not used and the
    // efficiency-based test decides, and refuses, with the option as without it. (That guarded
    // fit is without the likelihood descent of the unexplained candidates.)
    let g = random_geometry(9000, false).unwrap();
    let d = generate_calibration(&protocol(g.geometry, 0.01, 1001)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    for influence_move_test in [true, false] {
        let test_alone = SelectionConfig { more_likely_overrides_test: false, influence_move_test, ..measured };
        let cfg = OursConfig {
            noise: d.noise,
            selection: Some(test_alone),
            likelihood_descent: false,
            ..OursConfig::default()
        };
        let o = solve_ours_prepared(&set, &cfg).unwrap();
        assert!(
            matches!(o.selection_refused, Some(SelectionError::RanAway { statistic, limit, dof: 6, measured: false, .. }) if statistic > limit),
            "measured {influence_move_test}: {:?}",
            o.selection_refused
        );
    }
}
