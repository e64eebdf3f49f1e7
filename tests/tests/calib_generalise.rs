//! Calibration on random scene geometries: the generator, no mirror from a linear start in the
//! wrong basin, the typed ambiguity, degenerate lines, the visible-shaft selection region, the
//! shaft-position likelihood (shaft ends, its gradients, metre-noise data the lines alone
//! cannot calibrate), the best's mirror as a standing candidate, the left-out lines' likelihood,
//! the moving-covariance step (off by default), the likelihood descent of candidates the
//! refinement left unexplained, the search again from a cover of rotations when the fit is poor.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "test code (helpers too): a panic is a failed test"
)]

use estimator::calib::ours::{
    DEFAULT_MIN_LOG_LIKELIHOOD_RATIO, OursConfig, OursError, POOR_FIT_SCALE, solve_ours_prepared,
};
use estimator::calib::paper::{PaperConfig, PaperError, solve_paper_prepared};
use estimator::calib::prepare::{PENCIL_TOLERANCE, prepare};
use estimator::calib::selection::swept_box_probability;
use estimator::calib::{SelectionRule, pose_errors};
use nalgebra::{Matrix2, Vector2};
use rand::{Rng, SeedableRng};
use sim::calib::{CalibProtocol, NoiseUnits, generate_calibration, random_geometry};

fn protocol(seed: u64, distorted: bool, sigma: f64, units: NoiseUnits, trial: u64) -> CalibProtocol {
    let g = random_geometry(seed, distorted).unwrap();
    CalibProtocol { geometry: g.geometry, n_e: 3, n_t: 3, sigma, units, pixel_sigma_px: 0.0, seed: trial }
}

#[test]
fn random_geometries_are_repeatable_in_range_and_recovered_exactly_without_noise() {
    for (seed, distorted) in [(9000, false), (9001, true), (9004, false)] {
        let g = random_geometry(seed, distorted).unwrap();
        assert_eq!(g, random_geometry(seed, distorted).unwrap());
        assert!((0.08..=0.25).contains(&g.rcm_distance_m), "{}", g.rcm_distance_m);
        assert!((20f64.to_radians()..=70f64.to_radians()).contains(&g.tool_scope_angle_rad));
        assert_eq!(g.geometry.intrinsics.is_undistorted(), !distorted);
        assert_eq!(
            g.geometry.selection,
            SelectionRule { min_visible_shaft_px: 40.0, ends_are_shaft_ends: true, ..SelectionRule::default() }
        );
        let d = generate_calibration(&protocol(seed, distorted, 0.0, NoiseUnits::Millimetre, 0)).unwrap();
        let set = prepare(&d.setup, &d.observations).unwrap();
        let p = solve_paper_prepared(&set, &PaperConfig::default()).unwrap();
        let o = solve_ours_prepared(&set, &OursConfig::default()).unwrap();
        for e in [pose_errors(&p.pose, &d.truth), pose_errors(&o.pose, &d.truth)] {
            assert!(e.translation_m < 1e-8 && e.rotation_rad < 1e-8, "{seed}: {e:?}");
        }
    }
}

#[test]
fn a_linear_start_in_the_wrong_basin_does_not_give_the_mirror() {
    // Geometry 9000, millimetre reading, σ = 0.01, trial seed 1002: the linear start (and the
    // paper's pipeline) lands far from the truth; ours must not return a mirror.
    let d = generate_calibration(&protocol(9000, false, 0.01, NoiseUnits::Millimetre, 1002)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let p = solve_paper_prepared(&set, &PaperConfig::default()).unwrap();
    assert!(pose_errors(&p.pose, &d.truth).rotation_rad.to_degrees() > 90.0, "the case is not the one documented");
    let o = solve_ours_prepared(&set, &OursConfig { noise: d.noise, ..OursConfig::default() }).unwrap();
    let e = pose_errors(&o.pose, &d.truth);
    assert!(e.rotation_rad.to_degrees() < 2.0 && e.translation_m < 0.01, "{e:?}");
    assert!(o.log_likelihood_ratio.is_finite() && o.log_likelihood_ratio >= DEFAULT_MIN_LOG_LIKELIHOOD_RATIO);
}

#[test]
fn the_ambiguity_error_carries_both_candidates_and_their_likelihoods() {
    // Geometry 9010: the runner-up (the mirror) puts the shafts in front of the camera too.
    let d = generate_calibration(&protocol(9010, false, 0.01, NoiseUnits::Millimetre, 1000)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let ok = solve_ours_prepared(&set, &OursConfig { noise: d.noise, ..OursConfig::default() }).unwrap();
    // Demand more evidence than the data hold: the same decision becomes a typed refusal.
    let min = ok.log_likelihood_ratio * 2.0;
    let cfg = OursConfig { noise: d.noise, min_log_likelihood_ratio: min, ..OursConfig::default() };
    match solve_ours_prepared(&set, &cfg) {
        Err(OursError::Ambiguous { best, runner_up, log_likelihood_ratio, min: m, angle_deg, .. }) => {
            assert!(best.nll.is_finite() && runner_up.nll.is_finite());
            assert!((runner_up.nll - best.nll - log_likelihood_ratio).abs() < 1e-9 * best.nll.abs().max(1.0));
            assert!(log_likelihood_ratio < m && m == min);
            assert!(angle_deg > 10.0, "the runner-up is a distinct solution: {angle_deg}°");
            assert!(pose_errors(&best.pose, &d.truth).rotation_rad.to_degrees() < 2.0);
            assert!(estimator::calib::ours::explains_shafts(&set, &runner_up.pose));
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn a_runner_up_that_puts_the_shafts_behind_the_camera_is_no_rival() {
    // Geometry 9011, millimetre reading: the mirror fits the lines nearly as well, but puts the
    // shafts where no instrument is; even an absurd demand for evidence is no ambiguity then.
    // (The lines alone: with the shaft-position terms the refined mirror is pulled in front of
    // the camera, and is then an explaining rival, but thousands of nats less likely.)
    let d = generate_calibration(&protocol(9011, true, 0.01, NoiseUnits::Millimetre, 1000)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let cfg =
        OursConfig { noise: d.noise, min_log_likelihood_ratio: 1e12, shaft_position: false, ..OursConfig::default() };
    let o = solve_ours_prepared(&set, &cfg).unwrap();
    assert!(!estimator::calib::ours::explains_shafts(&set, &o.alternative));
    assert!(o.log_likelihood_ratio < 1e12);
    assert!(pose_errors(&o.pose, &d.truth).rotation_rad.to_degrees() < 2.0);
    let with = solve_ours_prepared(&set, &OursConfig { noise: d.noise, ..OursConfig::default() }).unwrap();
    assert!(with.log_likelihood_ratio > 1000.0, "{}", with.log_likelihood_ratio);
    assert!(pose_errors(&with.pose, &d.truth).rotation_rad.to_degrees() < 2.0);
}

#[test]
fn degenerate_lines_are_typed_errors_of_both_pipelines() {
    let d = generate_calibration(&protocol(9002, false, 0.0, NoiseUnits::Millimetre, 0)).unwrap();
    let mut identical = d.observations.clone();
    for o in &mut identical {
        o.line_px = d.observations[0].line_px;
    }
    let mut horizontal = d.observations.clone();
    for (i, o) in horizontal.iter_mut().enumerate() {
        let v = 100.0 + (i % 200) as f64;
        o.line_px = [[10.0, v], [600.0, v]];
    }
    for obs in [identical, horizontal] {
        let set = prepare(&d.setup, &obs).unwrap();
        assert!(set.pencil_ratio < 1e-6, "{}", set.pencil_ratio);
        let p = solve_paper_prepared(&set, &PaperConfig::default());
        assert!(matches!(p, Err(PaperError::LinesFormOnePencil { .. })), "{p:?}");
        let o = solve_ours_prepared(&set, &OursConfig::default());
        assert!(matches!(o, Err(OursError::LinesFormOnePencil { .. })), "{o:?}");
        // Valid data of the same geometry sit far above the tolerance.
        assert!(prepare(&d.setup, &d.observations).unwrap().pencil_ratio > 100.0 * PENCIL_TOLERANCE);
    }
}

#[test]
fn the_visible_shaft_region_probability_matches_sampling() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let s = Matrix2::new(400.0, 150.0, 150.0, 250.0);
    let ch = s.cholesky().unwrap().l();
    let (lo, hi) = (Vector2::new(-30.0, -50.0), Vector2::new(40.0, 20.0));
    for d in [Vector2::new(1.0, 0.0), Vector2::new(0.6, 0.8), Vector2::new(-0.8, 0.6)] {
        let p = swept_box_probability(&s, &lo, &hi, &d);
        let n = 200_000;
        let mut inside = 0;
        for _ in 0..n {
            let z =
                Vector2::new(rng.sample::<f64, _>(rand_distr::StandardNormal), rng.sample(rand_distr::StandardNormal));
            let x = ch * z;
            // In the swept box: the ray x + a d, a ≥ 0, meets the box.
            let hit = estimator::calib::selection::clip_line_to_box(&x, &d, &lo, &hi).is_some_and(|(_, b)| b >= 0.0);
            inside += usize::from(hit);
        }
        let mc = inside as f64 / n as f64;
        assert!((p - mc).abs() < 4e-3, "{d:?}: quadrature {p}, sampling {mc}");
        // Larger than the box alone, which it contains.
        assert!(p > estimator::calib::selection::box_probability(&s, &lo, &hi));
    }
}

#[test]
fn a_mirror_or_a_far_pose_does_not_explain_where_the_shafts_were_seen() {
    use estimator::calib::ours::{SHAFT_MARGIN, explains_shafts, shaft_explanation};
    use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};
    let d = generate_calibration(&protocol(9003, false, 0.0, NoiseUnits::Millimetre, 0)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let n = set.obs.len();
    // The truth puts every noiseless shaft in front of the camera, on the instrument.
    let x = shaft_explanation(&set, &d.truth, SHAFT_MARGIN);
    assert_eq!((x.behind, x.off_shaft, x.observations), (0, 0, n));
    assert!(explains_shafts(&set, &d.truth));
    // The mirror: 180° about the line of sight from the mean optical centre to robot 2's RCM,
    // the RCM kept in place. Its lines are the truth's lines; its shafts are behind the camera.
    let mean_c = set.obs.iter().map(|o| o.o_ec).sum::<Vector3<f64>>() / n as f64;
    let rcm = d.truth.translation.vector;
    let flip = UnitQuaternion::from_axis_angle(&Unit::new_normalize(rcm - mean_c), std::f64::consts::PI);
    let mirror = Isometry3::from_parts(Translation3::from(rcm), flip * d.truth.rotation);
    let x = shaft_explanation(&set, &mirror, SHAFT_MARGIN);
    let (behind, off) = (x.behind, x.off_shaft);
    assert!(behind + off > n / 2, "mirror: {behind} behind, {off} off of {n}");
    assert!(!explains_shafts(&set, &mirror));
    // The truth pushed 100× farther from the mean optical centre: every shaft in front, but
    // off the instrument (its image would be a hundred times shorter).
    let far = Isometry3::from_parts(Translation3::from(mean_c + (rcm - mean_c) * 100.0), d.truth.rotation);
    let x = shaft_explanation(&set, &far, SHAFT_MARGIN);
    let (behind, off) = (x.behind, x.off_shaft);
    assert!(off > n / 2, "far: {behind} behind, {off} off of {n}");
    assert!(!explains_shafts(&set, &far));
}

#[test]
fn a_solution_that_does_not_explain_the_shafts_is_never_returned() {
    use estimator::calib::ours::explains_shafts;
    // Tuning geometry 9000, metre reading, σ = 0.01, trial seed 1019: before the check the most
    // likely candidate was a mirror pushed 47 km away (every shaft off the instrument), and the
    // selection-aware stage was applied to it: a wrong pose with exit 0.
    let d = generate_calibration(&protocol(9000, false, 0.01, NoiseUnits::Metre, 1019)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    match solve_ours_prepared(&set, &OursConfig { noise: d.noise, ..OursConfig::default() }) {
        Ok(o) => {
            assert!(explains_shafts(&set, &o.pose), "returned a pose that does not explain the shafts");
            let e = pose_errors(&o.pose, &d.truth);
            assert!(e.rotation_rad.to_degrees() < 90.0, "{e:?}");
        }
        Err(OursError::ShaftsNotExplained { behind, off_shaft, observations, .. }) => {
            assert!(behind + off_shaft > observations / 10, "{behind} + {off_shaft} of {observations}");
        }
        Err(e) => panic!("unexpected error {e}"),
    }
}

#[test]
fn the_best_candidates_mirror_takes_part_and_the_most_likely_decides() {
    // Tuning geometry 9013 (distorted), metre reading, σ = 0.014, trial seed 1010: every start
    // went to the mirror basin; the shaft terms pulled that mirror in front of the camera far
    // enough to explain the shafts and it was returned, the selection stage applied: 179° off
    // with exit 0. With the best's mirrors refined as candidates, the true basin is found and
    // is far more likely; it puts 11 % of the shafts behind the camera (the truth itself 5 %),
    // so the data are refused, never answered with the less likely mirror.
    let d = generate_calibration(&protocol(9013, true, 0.014, NoiseUnits::Metre, 1010)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    match solve_ours_prepared(&set, &OursConfig { noise: d.noise, ..OursConfig::default() }) {
        Ok(o) => {
            let e = pose_errors(&o.pose, &d.truth);
            assert!(e.rotation_rad.to_degrees() < 90.0 || o.selection.is_none(), "mirror with exit 0: {e:?}");
        }
        Err(OursError::ShaftsNotExplained { pose, .. }) => {
            let e = pose_errors(&pose, &d.truth);
            assert!(e.rotation_rad.to_degrees() < 10.0, "the most likely candidate is not the true basin: {e:?}");
        }
        Err(e) => panic!("unexpected error {e}"),
    }
}

#[test]
fn a_line_the_first_order_model_leaves_out_costs_no_likelihood() {
    use estimator::calib::selection::{SelectionConfig, kept_given_line_ln};
    use nalgebra::{Unit, UnitQuaternion, Vector3};
    // With the first-order tip model trusted nowhere (depth ratio ~0) and no line plain (the
    // guard out of reach), every line is left out of the selection model: that says nothing
    // about the pose (0), except for a tip behind the camera (the floor, ln 1e-13).
    let d = generate_calibration(&protocol(9003, false, 0.01, NoiseUnits::Millimetre, 0)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let noise = d.noise.unwrap();
    let cfg = SelectionConfig { depth_ratio: 1e-12, plain_guard_sigmas: 1e9, ..SelectionConfig::default() };
    let r = d.truth.rotation.to_rotation_matrix().into_inner();
    let t = d.truth.translation.vector;
    for o in &set.obs {
        assert_eq!(kept_given_line_ln(&set, o, &r, &t, &noise, &cfg), 0.0);
    }
    // The mirror puts most tips behind the camera: those are the floor.
    let n = set.obs.len() as f64;
    let mean_c = set.obs.iter().map(|o| o.o_ec).sum::<Vector3<f64>>() / n;
    let flip = UnitQuaternion::from_axis_angle(&Unit::new_normalize(t - mean_c), std::f64::consts::PI);
    let rm = (flip * d.truth.rotation).to_rotation_matrix().into_inner();
    let floor = set.obs.iter().filter(|o| kept_given_line_ln(&set, o, &rm, &t, &noise, &cfg) < -29.0).count();
    assert!(floor * 2 > set.obs.len(), "{floor} of {} tips behind the camera", set.obs.len());
}

#[test]
fn shaft_ends_are_recognised_and_place_the_tool() {
    use estimator::calib::selection::tip_at_end;
    use estimator::calib::shaft_position::{shaft_position_residuals, translation_from_shaft_ends};
    use nalgebra::{Isometry3, Translation3, Vector3};
    // Noiseless tuning geometry 9003: the tip is in view in some observations, not in others.
    let mut d = generate_calibration(&protocol(9003, false, 0.0, NoiseUnits::Millimetre, 0)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let ends: usize = set.obs.iter().map(|o| o.shaft_end.iter().filter(|e| **e).count()).sum();
    let points = 2 * set.obs.len();
    assert!(ends > 10 && ends < points, "{ends} shaft ends of {points} line points");
    let r = d.truth.rotation.to_rotation_matrix().into_inner();
    let t = d.truth.translation.vector;
    // The ends put the tool where it is, given its rotation (Eq. 5 cannot on noisy metre data).
    let te = translation_from_shaft_ends(&set, &r).unwrap();
    assert!((te - t).norm() < 1e-6, "{} m off", (te - t).norm());
    // At the truth every term is zero (the noise model of the millimetre reading at σ 0.01).
    let noise = estimator::calib::KinematicNoise { rot_rad: 0.01, trans_m: 1e-5, pixel_px: 0.0 };
    let mut tips = 0;
    for o in &set.obs {
        let e = shaft_position_residuals(&set, o, &r, &t, &noise);
        assert!(e.iter().all(|v| v.abs() < 1e-6), "{e:?}");
        tips += usize::from(tip_at_end(&set, o, &r, &t, &noise, 0.3).is_some());
    }
    assert!(tips > 5, "{tips} observations with the tip at a shaft end");
    // 20 mm along the tool: the lines barely change, the tips are many deviations off.
    let axis = set.obs.iter().map(|o| r * o.m_t).sum::<Vector3<f64>>().normalize();
    let moved = Isometry3::from_parts(Translation3::from(t + axis * 0.02), d.truth.rotation);
    let (rm, tm) = (moved.rotation.to_rotation_matrix().into_inner(), moved.translation.vector);
    let far = set.obs.iter().filter(|o| shaft_position_residuals(&set, o, &rm, &tm, &noise)[4].abs() > 3.0).count();
    assert!(far * 2 > tips, "{far} of {tips} tips more than 3 deviations off");
    // Without the dataset's statement the points are only on the shaft: no ends.
    d.setup.selection.ends_are_shaft_ends = false;
    let plain = prepare(&d.setup, &d.observations).unwrap();
    assert!(plain.obs.iter().all(|o| o.shaft_end == [false, false]));
    assert!(translation_from_shaft_ends(&plain, &r).is_none());
}

#[test]
fn the_shaft_positions_calibrate_where_the_lines_alone_cannot() {
    use estimator::calib::ours::explains_shafts;
    // Tuning geometry 9000, metre reading, σ = 0.01, trial seed 1000: every line-model optimum
    // the usual starts find puts over a tenth of the shafts behind the camera (refused); where
    // the shafts were seen along the lines places the tool. (The search from the cover of
    // rotations every time finds a line-model optimum in front of the camera here, 20 mm and
    // 0.5° off: the lines alone are compared from the usual starts.)
    let d = generate_calibration(&protocol(9000, false, 0.01, NoiseUnits::Metre, 1000)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let lines = OursConfig { noise: d.noise, shaft_position: false, cover_search_scale: None, ..OursConfig::default() };
    let r = solve_ours_prepared(&set, &lines);
    assert!(matches!(r, Err(OursError::ShaftsNotExplained { .. })), "{r:?}");
    let o = solve_ours_prepared(&set, &OursConfig { noise: d.noise, ..OursConfig::default() }).unwrap();
    let e = pose_errors(&o.pose, &d.truth);
    assert!(e.translation_m < 0.01 && e.rotation_rad.to_degrees() < 1.5, "{e:?}");
    assert!(explains_shafts(&set, &o.pose));
    assert!(o.selection.is_some(), "the selection-aware stage is applied: {:?}", o.selection_refused);
}

#[test]
fn the_shaft_position_gradients_match_differences() {
    use estimator::calib::shaft_position::{TERMS, residuals_and_gradients_at, residuals_at, shaft_model};
    use nalgebra::{Rotation3, Vector3, Vector6};
    let d = generate_calibration(&protocol(9002, false, 0.01, NoiseUnits::Metre, 1001)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let noise = d.noise.unwrap();
    // 60 mm and a few degrees off the truth: points off the shaft, some tips far off.
    let r = Rotation3::new(Vector3::new(0.03, -0.05, 0.02)).into_inner()
        * d.truth.rotation.to_rotation_matrix().into_inner();
    let t = d.truth.translation.vector + Vector3::new(0.03, -0.04, 0.03);
    let mut checked = [0usize; TERMS];
    for o in &set.obs {
        let m = shaft_model(&set, o, &r, &t, &noise);
        let (e, g) = residuals_and_gradients_at(&set, o, &r, &t, &m);
        for k in 0..6 {
            let h = 1e-7;
            let at = |sg: f64| {
                let mut dv = Vector6::zeros();
                dv[k] = sg * h;
                let rr = Rotation3::new(dv.fixed_rows::<3>(3).into_owned()).into_inner() * r;
                residuals_at(&set, o, &rr, &(t + dv.fixed_rows::<3>(0)), &m)
            };
            let (p, q) = (at(1.0), at(-1.0));
            for i in 0..TERMS {
                // Only where the term is active on both sides (the penalties have kinks).
                if e[i] == 0.0 || p[i] == 0.0 || q[i] == 0.0 {
                    continue;
                }
                let num = (p[i] - q[i]) / (2.0 * h);
                let tol = 1e-4 * (num.abs() + g[i][k].abs()) + 1e-3;
                assert!((num - g[i][k]).abs() < tol, "term {i}, component {k}: numeric {num}, analytic {}", g[i][k]);
                if k == 0 {
                    checked[i] += 1;
                }
            }
        }
    }
    assert!(checked[0] + checked[1] > 10 && checked[4] > 10, "{checked:?}");
}

#[test]
fn a_noise_model_without_the_arms_noise_calibrates_on_the_lines_alone() {
    // Tuning geometry 9000, millimetre reading, σ = 0.01, trial seed 1000, solved with a
    // pixel-only noise model (as `from-run` has for a recorded run): the shaft-position terms,
    // which say where the arms put the tool, are off, so the result is the lines' alone; with
    // the arms' noise they are on and the result differs.
    let d = generate_calibration(&protocol(9000, false, 0.01, NoiseUnits::Millimetre, 1000)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let pixels = estimator::calib::KinematicNoise { rot_rad: 0.0, trans_m: 0.0, pixel_px: 0.5 };
    assert!(!pixels.has_kinematic_terms() && d.noise.unwrap().has_kinematic_terms());
    let with = |noise, shaft_position| {
        solve_ours_prepared(&set, &OursConfig { noise: Some(noise), shaft_position, ..OursConfig::default() }).unwrap()
    };
    let (on, off) = (with(pixels, true), with(pixels, false));
    assert_eq!(on.pose, off.pose);
    let e = pose_errors(&on.pose, &d.truth);
    assert!(e.translation_m < 0.01 && e.rotation_rad.to_degrees() < 1.0, "{e:?}");
    let kin = d.noise.unwrap();
    assert_ne!(with(kin, true).pose, with(kin, false).pose);
}

#[test]
fn a_noise_model_stated_too_large_is_rescaled_by_the_fit() {
    // Tuning geometry 9000, millimetre reading, σ = 0.01, trial seed 1000, solved with the
    // true noise model and with one stated 20× too large (a cautious user's guess). Estimating
    // the scale finds the factor back (the fit's robust scale) and gives the true model's
    // result; taking the large model as stated does not.
    let d = generate_calibration(&protocol(9000, false, 0.01, NoiseUnits::Millimetre, 1000)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let truth_noise = d.noise.unwrap();
    let solve = |noise: estimator::calib::KinematicNoise, estimate_noise_scale| {
        solve_ours_prepared(&set, &OursConfig { noise: Some(noise), estimate_noise_scale, ..OursConfig::default() })
            .unwrap()
    };
    let right = solve(truth_noise, false);
    let stated = solve(truth_noise.scaled(20.0), false);
    let estimated = solve(truth_noise.scaled(20.0), true);
    let (er, es, ee) = (
        pose_errors(&right.pose, &d.truth),
        pose_errors(&stated.pose, &d.truth),
        pose_errors(&estimated.pose, &d.truth),
    );
    assert_eq!(right.noise_scale, None);
    let k = estimated.noise_scale.expect("the scale was estimated");
    assert!((k * 20.0 - 1.0).abs() < 0.3, "{k}");
    assert!((estimated.scale - 1.0).abs() < 0.2, "{}", estimated.scale);
    // As good as with the true model; the model taken as stated is much worse (on this trial
    // 1.8° against 0.19°: most lines fitted as plain or left out of the selection stage).
    assert!(ee.rotation_rad < 1.2 * er.rotation_rad && ee.translation_m < 1.2 * er.translation_m, "{ee:?} {er:?}");
    assert!(es.rotation_rad > 2.0 * ee.rotation_rad, "{es:?} {ee:?}");
}

#[test]
fn the_shaft_extent_says_where_a_line_may_lie_along_the_tool() {
    use estimator::calib::shaft_position::shaft_position_residuals;
    use estimator::calib::{Observation, ShaftExtent, rcm_arms::psm_axis};
    use nalgebra::Vector3;
    // Noiseless tuning geometry 9003 (points only on the shaft). Each tool line's known point
    // moved 150 mm toward the tip (the shafts are seen from 137 mm on) and the tip 10 mm back: the same lines, but now part of the
    // seen shafts lies before the point or past the tip. The default extent (RCM to tip)
    // counts those points as off the instrument; an extent that covers the 10 mm does not.
    let mut d = generate_calibration(&protocol(9003, false, 0.0, NoiseUnits::Millimetre, 0)).unwrap();
    d.setup.selection.ends_are_shaft_ends = false;
    let shifted: Vec<Observation> = d
        .observations
        .iter()
        .map(|o| {
            let m = psm_axis(&o.psm_joints);
            let p = Vector3::from(o.tool_point_m) + m * 0.15;
            Observation::from_tool_line(o.ecm_joints, p.into(), m.into(), o.psm_joints[2] - 0.16, o.line_px, o.eye)
                .unwrap()
        })
        .collect();
    let (r, t) = (d.truth.rotation.to_rotation_matrix().into_inner(), d.truth.translation.vector);
    let noise = estimator::calib::KinematicNoise { rot_rad: 0.01, trans_m: 1e-5, pixel_px: 0.0 };
    // Line points off the visible instrument: [before the point, past the tip].
    let off = |extent: ShaftExtent| {
        let set = prepare(&estimator::calib::Setup { shaft_extent: extent, ..d.setup }, &shifted).unwrap();
        set.obs.iter().fold([0, 0], |mut n, o| {
            let e = shaft_position_residuals(&set, o, &r, &t, &noise);
            for v in &e[..2] {
                n[0] += usize::from(*v < -1e-9);
                n[1] += usize::from(*v > 1e-9);
            }
            n
        })
    };
    let tight = off(ShaftExtent::default());
    assert!(tight[0] > 10 && tight[1] > 10, "{tight:?}");
    assert_eq!(off(ShaftExtent { beyond_tip_m: 0.0105, before_point_m: 0.0, end_sd_px: 0.0 })[1], 0);
    assert_eq!(off(ShaftExtent { beyond_tip_m: 0.0105, before_point_m: 0.1505, end_sd_px: 0.0 }), [0, 0]);
    assert_eq!(off(ShaftExtent { beyond_tip_m: 0.0, before_point_m: 0.1505, end_sd_px: 0.0 }), [0, tight[1]]);
    // The detector's end precision widens where a point may lie: the same excesses, fewer
    // deviations.
    let largest = |end_sd_px: f64| {
        let extent = ShaftExtent { end_sd_px, ..ShaftExtent::default() };
        let set = prepare(&estimator::calib::Setup { shaft_extent: extent, ..d.setup }, &shifted).unwrap();
        set.obs.iter().map(|o| shaft_position_residuals(&set, o, &r, &t, &noise)[1].abs()).fold(0.0, f64::max)
    };
    assert!(largest(8.0) < 0.6 * largest(0.0), "{} {}", largest(8.0), largest(0.0));
    // A negative or non-finite extent is refused.
    let bad = estimator::calib::Setup {
        shaft_extent: ShaftExtent { beyond_tip_m: -0.1, before_point_m: 0.0, end_sd_px: 0.0 },
        ..d.setup
    };
    assert!(matches!(prepare(&bad, &shifted), Err(estimator::calib::prepare::PrepareError::ShaftExtent(_))));
}

#[test]
fn the_moving_covariance_step_is_on_by_default_and_taken_only_where_it_significantly_adds_information() {
    use estimator::calib::selection::{MOVING_STEP_GAIN_Z, MOVING_STEP_MIN_GAIN, SelectionConfig};
    let solve = |seed: u64, units: NoiseUnits, sigma: f64, trial: u64, on: bool| {
        let d = generate_calibration(&protocol(seed, seed % 2 == 1, sigma, units, trial)).unwrap();
        let set = prepare(&d.setup, &d.observations).unwrap();
        let selection = Some(SelectionConfig { moving_covariance_step: on, ..SelectionConfig::default() });
        let r = solve_ours_prepared(&set, &OursConfig { noise: d.noise, selection, ..OursConfig::default() }).unwrap();
        let s = r.selection.expect("the selection stage is applied in these trials");
        (pose_errors(&r.pose, &d.truth), s.moving_step, r.pose)
    };
    // On by default, gated on the gain's own standard error.
    let default = SelectionConfig::default();
    assert!(default.moving_covariance_step);
    assert!(default.moving_step_gain_z == MOVING_STEP_GAIN_Z && MOVING_STEP_GAIN_Z > 0.0);
    assert_eq!(solve(9004, NoiseUnits::Metre, 0.01, 1002, false).1, None);
    // Tuning geometry 9004, metres, σ = 0.01, trial 2: the covariances' dependence on the pose
    // adds several times the held fit's information (gain ≈ 5.0, standard error ≈ 0.9) and the
    // step takes the rotation from 0.50° to 0.11° (translation 10.8 → 8.0 mm).
    let (held, _, _) = solve(9004, NoiseUnits::Metre, 0.01, 1002, false);
    let (moved, step, _) = solve(9004, NoiseUnits::Metre, 0.01, 1002, true);
    let (gain, gain_sd, taken) = step.expect("the step is computed");
    let gain_sd = gain_sd.expect("a gain above the threshold has its standard error");
    assert!(taken && gain - MOVING_STEP_GAIN_Z * gain_sd >= MOVING_STEP_MIN_GAIN, "gain {gain} ± {gain_sd}");
    assert!(moved.rotation_rad < 0.5 * held.rotation_rad, "{moved:?} vs {held:?}");
    assert!(moved.translation_m < held.translation_m, "{moved:?} vs {held:?}");
    // Tuning geometry 9000, millimetres, σ = 0.02, trial 0: it adds little (gain < 1), the
    // step is not taken and the pose is the one without the step.
    let (_, _, off_pose) = solve(9000, NoiseUnits::Millimetre, 0.02, 1000, false);
    let (_, step, pose) = solve(9000, NoiseUnits::Millimetre, 0.02, 1000, true);
    let (gain, gain_sd, taken) = step.expect("the step is computed");
    assert!(!taken && gain < MOVING_STEP_MIN_GAIN, "gain {gain}");
    // Below the threshold its standard error cannot change the decision: not computed.
    assert_eq!(gain_sd, None);
    assert_eq!(pose, off_pose);
    // Tuning geometry 9012, metres, σ = 0.005, trial 0: a spike of the gain (≈ 45; the
    // reading's median is below 1) that a few observations carry: its jackknife standard
    // error is as large as the gain itself, so it is not significant and the step is not taken
    // (session 20's gate, the gain as measured, would take it). Session 21's example, 9003 in
    // millimetres, went with the instrument through the lens (session 22's solid bodies).
    let (_, _, off_pose) = solve(9012, NoiseUnits::Metre, 0.005, 1000, false);
    let (_, step, pose) = solve(9012, NoiseUnits::Metre, 0.005, 1000, true);
    let (gain, gain_sd, taken) = step.expect("the step is computed");
    let gain_sd = gain_sd.expect("a gain above the threshold has its standard error");
    assert!(gain > 2.0 * MOVING_STEP_MIN_GAIN && gain_sd > 0.5 * gain && !taken, "gain {gain} ± {gain_sd}");
    assert_eq!(pose, off_pose);
}

#[test]
fn a_candidate_the_refinement_walks_out_of_the_physical_region_descends_back() {
    use estimator::calib::ours::explains_shafts;
    // Tuning geometry 9017 (distorted), metre reading, σ = 0.02, trial seed 1018: the true
    // basin's candidates ended, after the refinement's surrogate objective, with 96 shafts
    // behind the camera; left out as explanations, the mirror was the most likely candidate that
    // explained the shafts and was returned, 179° off, with exit 0 (its stage taken on its
    // likelihood). Descending the candidates' own likelihood brings the true basin back: it is
    // far more likely than the mirror (the truth itself by 7 764 nats).
    let d = generate_calibration(&protocol(9017, true, 0.02, NoiseUnits::Metre, 1018)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let cfg = OursConfig { noise: d.noise, ..OursConfig::default() };
    assert!(cfg.likelihood_descent, "on by default");
    let o = solve_ours_prepared(&set, &cfg).unwrap();
    let e = pose_errors(&o.pose, &d.truth);
    assert!(e.rotation_rad.to_degrees() < 10.0, "{e:?}");
    assert!(explains_shafts(&set, &o.pose));
    assert!(o.selection.is_some(), "the selection stage was refused: {:?}", o.selection_refused);
    // Without the descent (and without the search from the cover of rotations, the other
    // defence): the mirror (the case this guards against).
    let off = solve_ours_prepared(&set, &OursConfig { likelihood_descent: false, cover_search_scale: None, ..cfg });
    assert!(pose_errors(&off.unwrap().pose, &d.truth).rotation_rad.to_degrees() > 90.0);
    // Without the descent, the mirror fits worse than the noise model predicts, and the
    // search from the cover of rotations does not answer with it (it finds a pose 25° off whose
    // selection-aware stage is refused: a non-zero exit, not a confident wrong answer).
    match solve_ours_prepared(&set, &OursConfig { likelihood_descent: false, ..cfg }) {
        Ok(x) => {
            assert!(x.cover_searched);
            let e = pose_errors(&x.pose, &d.truth);
            assert!(e.rotation_rad.to_degrees() < 90.0, "{e:?}");
            assert!(e.rotation_rad.to_degrees() < 10.0 || x.selection_refused.is_some(), "{e:?}");
        }
        Err(e) => assert!(!matches!(e, OursError::Prepare(_)), "{e}"),
    }
}

#[test]
fn every_basin_is_judged_at_its_descended_likelihood() {
    use estimator::calib::ours::explains_shafts;
    // Tuning geometry 9005 (distorted), metre reading, σ = 0.02, trial seed 1014: every
    // candidate of the true basin explains the shafts, so none descended, and the refinement
    // had left them 1 800-3 000 nats less likely than the truth; the mirror won by 670 nats
    // (its stage refused: a non-zero exit, but the guarded fit was the mirror). Descended,
    // the true basin is the more likely by over 1 000 nats. From the usual starts: searched from
    // the cover of rotations every time, a still more likely candidate puts 186 of 393 shafts
    // behind the camera and the data are refused (`ShaftsNotExplained`).
    let d = generate_calibration(&protocol(9005, true, 0.02, NoiseUnits::Metre, 1014)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let cfg = OursConfig { noise: d.noise, cover_search_scale: None, ..OursConfig::default() };
    // Either way, no confident wrong answer.
    match solve_ours_prepared(&set, &OursConfig { cover_search_scale: Some(0.0), ..cfg }) {
        Ok(x) => assert!(pose_errors(&x.pose, &d.truth).rotation_rad.to_degrees() < 10.0, "{:?}", x.pose),
        Err(e) => assert!(matches!(e, OursError::ShaftsNotExplained { .. } | OursError::Ambiguous { .. }), "{e}"),
    }
    assert!(cfg.descend_every_basin, "on by default");
    let o = solve_ours_prepared(&set, &cfg).unwrap();
    let e = pose_errors(&o.pose, &d.truth);
    assert!(e.rotation_rad.to_degrees() < 5.0 && e.translation_m < 0.05, "{e:?}");
    assert!(explains_shafts(&set, &o.pose));
    assert!(o.log_likelihood_ratio > 1000.0, "{}", o.log_likelihood_ratio);
    // Without it: the mirror.
    let off = solve_ours_prepared(&set, &OursConfig { descend_every_basin: false, ..cfg }).unwrap();
    assert!(pose_errors(&off.pose, &d.truth).rotation_rad.to_degrees() > 90.0);
}

#[test]
fn a_fit_worse_than_the_noise_model_is_searched_again_from_a_cover_of_rotations() {
    // Tuning geometry 9038 (undistorted), metre reading, σ = 0.02, trial seed 1011: the linear
    // start, its 180° turns, the other minima of Eq. 10 and the best's mirrors all miss the
    // true basin, and the search answers with a mirror that fits 1.6 times worse than the
    // noise model predicts (only the selection-aware stage's move test refused it). Searched
    // again from the cover of rotation space (the poor-fit trigger, `POOR_FIT_SCALE`), the
    // true basin is found and is the answer; the cover every time (the default) finds it too.
    let d = generate_calibration(&protocol(9038, false, 0.02, NoiseUnits::Metre, 1011)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let default = OursConfig { noise: d.noise, selection: None, ..OursConfig::default() };
    assert_eq!(default.cover_search_scale, Some(0.0), "the cover every time by default");
    let limit = POOR_FIT_SCALE;
    let cfg = OursConfig { cover_search_scale: Some(limit), ..default };
    let always = solve_ours_prepared(&set, &default).unwrap();
    assert!(always.cover_searched);
    let e = pose_errors(&always.pose, &d.truth);
    assert!(e.rotation_rad.to_degrees() < 5.0 && e.translation_m < 0.05, "{e:?}");
    let narrow = solve_ours_prepared(&set, &OursConfig { cover_search_scale: None, ..cfg }).unwrap();
    assert!(!narrow.cover_searched);
    assert!(narrow.scale > limit, "the case is not the one documented: scale {}", narrow.scale);
    let e = pose_errors(&narrow.pose, &d.truth);
    assert!(e.rotation_rad.to_degrees() > 170.0, "the case is not the one documented: {e:?}");
    let o = solve_ours_prepared(&set, &cfg).unwrap();
    assert!(o.cover_searched);
    let e = pose_errors(&o.pose, &d.truth);
    assert!(e.rotation_rad.to_degrees() < 5.0 && e.translation_m < 0.05, "{e:?}");
    assert!(o.scale < narrow.scale, "{} against {}", o.scale, narrow.scale);
    // A fit as good as the noise model predicts (same geometry, trial seed 1000) is not
    // searched again.
    let d = generate_calibration(&protocol(9038, false, 0.02, NoiseUnits::Metre, 1000)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let o = solve_ours_prepared(&set, &OursConfig { noise: d.noise, selection: None, ..cfg }).unwrap();
    assert!(o.scale <= limit && !o.cover_searched, "scale {}", o.scale);
}

#[test]
fn a_search_from_the_cover_every_time_finds_a_basin_the_usual_starts_miss_under_a_good_fit() {
    // Tuning geometry 9093 (distorted), metre reading, σ = 0.02, trial seed 1002: the usual
    // starts miss the true basin and the mirror they find fits about as well as the noise model
    // predicts (robust scale under the poor-fit trigger `POOR_FIT_SCALE`, the default until
    // session 31), so the trigger does not search again, and the mirror is the answer (its
    // selection-aware stage applied: exit 0). Searched from the cover every time (the
    // default), the true basin is found, the more likely.
    let d = generate_calibration(&protocol(9093, true, 0.02, NoiseUnits::Metre, 1002)).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let cfg = OursConfig { noise: d.noise, selection: None, ..OursConfig::default() };
    let usual = solve_ours_prepared(&set, &OursConfig { cover_search_scale: Some(POOR_FIT_SCALE), ..cfg }).unwrap();
    assert!(!usual.cover_searched, "scale {}", usual.scale);
    let e = pose_errors(&usual.pose, &d.truth);
    assert!(e.rotation_rad.to_degrees() > 170.0, "the case is not the one documented: {e:?}");
    let always = solve_ours_prepared(&set, &cfg).unwrap();
    assert!(always.cover_searched);
    let e = pose_errors(&always.pose, &d.truth);
    assert!(e.rotation_rad.to_degrees() < 5.0 && e.translation_m < 0.05, "{e:?}");
}
