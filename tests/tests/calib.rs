//! Dual RCM-arm calibration: exact recovery, degenerate cases, known answers, ambiguity,
//! robustness, the noise Jacobian and the Cramér-Rao bound (simulated data from `sim`).
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use estimator::calib::crb::cramer_rao_bound;
use estimator::calib::ours::DEFAULT_MIN_LOG_LIKELIHOOD_RATIO;
use estimator::calib::ours::{OursConfig, OursError, solve_ours, solve_ours_prepared};
use estimator::calib::paper::{
    PaperConfig, PaperError, eq10_w, kronecker_row, project_to_so3, refine_quaternion, solve_paper, wxyz,
};
use estimator::calib::prepare::{PrepareError, Prepared, PreparedSet, prepare};
use estimator::calib::rcm_arms::se3_exp;
use estimator::calib::residual::{noise_jacobian, residual_and_jacobian};
use estimator::calib::{KinematicNoise, Observation, pose_errors};
use nalgebra::{
    Isometry3, Matrix3, Point3, Rotation3, SVector, Translation3, UnitQuaternion, Vector2, Vector3, Vector4,
};
use sim::calib::{CalibDataset, CalibGeometry, CalibProtocol, NoiseUnits, generate_calibration};

fn protocol(n_e: usize, n_t: usize, sigma: f64, units: NoiseUnits, seed: u64) -> CalibProtocol {
    CalibProtocol { geometry: CalibGeometry::default(), n_e, n_t, sigma, units, pixel_sigma_px: 0.0, seed }
}

fn data(n_e: usize, n_t: usize, sigma: f64, units: NoiseUnits, seed: u64) -> CalibDataset {
    generate_calibration(&protocol(n_e, n_t, sigma, units, seed)).unwrap()
}

#[test]
fn noiseless_data_are_recovered_exactly_by_both_pipelines() {
    for (n_e, n_t) in [(2, 2), (3, 3)] {
        let d = data(n_e, n_t, 0.0, NoiseUnits::Millimetre, 0);
        assert!(d.dropped > 0 && d.observations.len() + d.dropped == d.generated);
        let p = solve_paper(&d.setup, &d.observations, &PaperConfig::default()).unwrap();
        let e = pose_errors(&p.pose, &d.truth);
        assert!(e.translation_m < 1e-9 && e.rotation_rad < 1e-9, "paper {e:?}");
        let o = solve_ours(&d.setup, &d.observations, &OursConfig::default()).unwrap();
        let e = pose_errors(&o.pose, &d.truth);
        assert!(e.translation_m < 1e-9 && e.rotation_rad < 1e-9, "ours {e:?}");
        assert!(o.residuals.rms_px < 1e-6, "{:?}", o.residuals);
        assert!(
            o.log_likelihood_ratio.is_finite() && o.log_likelihood_ratio > 10.0 * DEFAULT_MIN_LOG_LIKELIHOOD_RATIO,
            "noiseless data are unambiguous: {}",
            o.log_likelihood_ratio
        );
    }
}

/// Both pipelines refuse `d` with the same preparation error.
fn both_refuse(d: &sim::calib::CalibDataset, want: PrepareError) {
    assert_eq!(
        solve_paper(&d.setup, &d.observations, &PaperConfig::default()).unwrap_err(),
        PaperError::Prepare(want.clone())
    );
    assert_eq!(solve_ours(&d.setup, &d.observations, &OursConfig::default()).unwrap_err(), OursError::Prepare(want));
}

#[test]
fn one_view_of_robot_1_is_its_own_error() {
    let mut p = protocol(2, 3, 0.0, NoiseUnits::Millimetre, 0);
    p.geometry.ecm_yaw_rad = [0.05; 2];
    p.geometry.ecm_pitch_rad = [0.0; 2];
    p.geometry.ecm_insertion_m = [0.08; 2];
    p.geometry.ecm_roll_rad = [0.0; 2];
    let d = generate_calibration(&p).unwrap();
    both_refuse(&d, PrepareError::TooFewViews { views: 1 });
}

#[test]
fn two_tool_orientations_are_their_own_error() {
    let mut p = protocol(2, 2, 0.0, NoiseUnits::Millimetre, 0);
    p.geometry.psm_pitch_rad = [0.0; 2]; // yaw only: two orientations
    let d = generate_calibration(&p).unwrap();
    both_refuse(&d, PrepareError::TooFewToolOrientations { orientations: 2 });
}

#[test]
fn views_collinear_with_robot_2s_rcm_are_their_own_error() {
    // Robot 2's RCM on robot 1's shaft axis; the endoscope only inserts (no yaw, pitch,
    // roll; centred camera): every optical centre lies on the line to robot 2's RCM.
    let mut g = CalibGeometry { hand_eye: Isometry3::identity(), ..Default::default() };
    let t = Vector3::new(0.0, 0.0, 0.25);
    let aim = (Vector3::new(0.04, 0.01, 0.16) - t).normalize();
    g.truth =
        Isometry3::from_parts(Translation3::from(t), UnitQuaternion::rotation_between(&Vector3::z(), &aim).unwrap());
    g.ecm_yaw_rad = [0.0; 2];
    g.ecm_pitch_rad = [0.0; 2];
    g.ecm_roll_rad = [0.0; 2];
    g.psm_insertion_m = 0.07;
    let d = generate_calibration(&CalibProtocol::noiseless(g)).unwrap();
    assert!(d.observations.len() >= 9, "kept {}", d.observations.len());
    assert!(matches!(
        solve_paper(&d.setup, &d.observations, &PaperConfig::default()),
        Err(PaperError::ViewsCollinear { .. })
    ));
    assert!(matches!(
        solve_ours(&d.setup, &d.observations, &OursConfig::default()),
        Err(OursError::ViewsCollinear { .. })
    ));
    // The same scene with sideways endoscope motion is fine.
    let mut g2 = g;
    g2.ecm_yaw_rad = [-0.1, 0.1];
    let d2 = generate_calibration(&CalibProtocol {
        geometry: g2,
        n_e: 3,
        n_t: 3,
        sigma: 0.0,
        units: NoiseUnits::Millimetre,
        pixel_sigma_px: 0.0,
        seed: 0,
    })
    .unwrap();
    let e = pose_errors(&solve_paper(&d2.setup, &d2.observations, &PaperConfig::default()).unwrap().pose, &d2.truth);
    assert!(e.translation_m < 1e-9, "{e:?}");
}

#[test]
fn bad_input_gets_typed_errors() {
    let d = data(2, 2, 0.0, NoiseUnits::Millimetre, 0);
    assert_eq!(prepare(&d.setup, &[]).unwrap_err(), PrepareError::Empty);
    let mut obs = d.observations.clone();
    obs[3].line_px[1] = obs[3].line_px[0];
    assert!(matches!(prepare(&d.setup, &obs), Err(PrepareError::Line { index: 3, .. })));
    let mut obs = d.observations.clone();
    obs[1].ecm_joints[2] = f64::NAN;
    assert_eq!(prepare(&d.setup, &obs).unwrap_err(), PrepareError::Joint { index: 1 });
    let mut setup = d.setup;
    setup.intrinsics.fx = -1.0;
    assert!(matches!(prepare(&setup, &d.observations), Err(PrepareError::Intrinsics(_))));
    let bad_noise = OursConfig {
        noise: Some(KinematicNoise { rot_rad: -1.0, trans_m: 0.0, pixel_px: 0.0 }),
        ..OursConfig::default()
    };
    assert_eq!(solve_ours(&d.setup, &d.observations, &bad_noise).unwrap_err(), OursError::NoiseModel);
}

#[test]
fn kronecker_row_and_so3_projection_known_answers() {
    let r = Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(Vector3::new(1.0, 2.0, 3.0)), 0.7).into_inner();
    let n = Vector3::new(0.3, -0.4, 0.5);
    let m = Vector3::new(-0.2, 0.9, 0.1);
    // kᵀ Vec(R) = nᵀ R m with the column-major Vec of Appendix A.
    let vec_r = SVector::<f64, 9>::from_column_slice(r.as_slice());
    assert!((kronecker_row(&n, &m).dot(&vec_r) - n.dot(&(r * m))).abs() < 1e-15);
    // Eq. 9: the sign and scale of V do not matter.
    for s in [2.5, -0.3] {
        assert!((project_to_so3(&(r * s)).into_inner() - r).norm() < 1e-12, "s = {s}");
    }
    // Remark 1: a non-orthogonal V projects to the nearest rotation.
    let skewed = r + Matrix3::new(0.0, 1e-3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let p = project_to_so3(&skewed);
    assert!((p.into_inner() - r).norm() < 2e-3 && (p.matrix().determinant() - 1.0).abs() < 1e-12);
}

#[test]
fn quaternion_form_of_eq10_and_its_refinement() {
    let q = UnitQuaternion::from_euler_angles(0.4, -1.1, 2.0);
    let (n, m) = (Vector3::new(0.2, 0.7, -0.3), Vector3::new(-0.5, 0.1, 0.8));
    let w = eq10_w(&n, &m);
    let v = wxyz(&q);
    assert!((v.dot(&(w * v)) - n.dot(&(q * m))).abs() < 1e-14);
    // From 25° off, Eq. 10 returns the true rotation on noiseless data.
    let d = data(2, 2, 0.0, NoiseUnits::Millimetre, 0);
    let set = prepare(&d.setup, &d.observations).unwrap();
    let start = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 25f64.to_radians()) * d.truth.rotation;
    let (q, cost, it) = refine_quaternion(&set, &(wxyz(&start) * 3.0));
    assert!(
        q.angle_to(&d.truth.rotation) < 1e-9 && cost < 1e-20 && it > 1,
        "{} {cost} {it}",
        q.angle_to(&d.truth.rotation)
    );
    // A zero start is replaced by the identity instead of producing NaN.
    let (q0, c0, _) = refine_quaternion(&set, &Vector4::zeros());
    assert!(q0.coords.iter().all(|x| x.is_finite()) && c0.is_finite());
}

#[test]
fn the_mirrored_solution_is_detected_and_resolved() {
    let d = data(3, 3, 0.01, NoiseUnits::Millimetre, 3);
    let set = prepare(&d.setup, &d.observations).unwrap();
    let good = solve_ours_prepared(&set, &OursConfig { noise: d.noise, ..OursConfig::default() }).unwrap();
    assert!(good.log_likelihood_ratio >= DEFAULT_MIN_LOG_LIKELIHOOD_RATIO, "{}", good.log_likelihood_ratio);
    // The mirror: 180° about the line of sight to robot 2's RCM.
    let flip_deg = (good.alternative.rotation.inverse() * good.pose.rotation).angle().to_degrees();
    assert!(flip_deg > 150.0, "alternative {flip_deg}° away");
    // Started on the mirror, ours still lands on the right solution.
    let mean_c = set.obs.iter().map(|o| o.o_ec).sum::<Vector3<f64>>() / set.obs.len() as f64;
    let axis = nalgebra::Unit::new_normalize(d.truth.translation.vector - mean_c);
    let mirror = UnitQuaternion::from_axis_angle(&axis, std::f64::consts::PI) * d.truth.rotation;
    let from_mirror = solve_ours_prepared(
        &set,
        &OursConfig { noise: d.noise, initial_quaternion: Some(wxyz(&mirror).into()), ..OursConfig::default() },
    )
    .unwrap();
    let gap = from_mirror.pose.rotation.angle_to(&good.pose.rotation);
    assert!(gap < 1e-5, "{gap}");
    // Eq. 10 alone, started on the mirror, stays near it (a local minimum).
    let (q, _, _) = refine_quaternion(&set, &wxyz(&mirror));
    assert!(q.angle_to(&d.truth.rotation).to_degrees() > 90.0);
}

#[test]
fn outlier_lines_are_down_weighted() {
    let d = data(3, 3, 0.0, NoiseUnits::Millimetre, 0);
    let mut obs = d.observations.clone();
    let n = obs.len();
    for (k, o) in obs.iter_mut().enumerate().filter(|(k, _)| k % 10 == 0) {
        // A wrong line (e.g. an instrument edge or another tool): shifted and turned.
        o.line_px = [[50.0 + k as f64 % 200.0, 400.0], [600.0, 30.0 + (k * 7) as f64 % 300.0]];
    }
    let p = solve_paper(&d.setup, &obs, &PaperConfig::default()).unwrap();
    let cfg = OursConfig {
        noise: Some(KinematicNoise { rot_rad: 0.0, trans_m: 0.0, pixel_px: 0.5 }),
        selection: None,
        ..OursConfig::default()
    };
    let o = solve_ours(&d.setup, &obs, &cfg).unwrap();
    let (ep, eo) = (pose_errors(&p.pose, &d.truth), pose_errors(&o.pose, &d.truth));
    assert!(eo.translation_m < 1e-6 && eo.rotation_rad < 1e-6, "ours {eo:?}");
    // The selection-aware stage leaves the outliers out too; on noise-free lines its
    // selection terms pull the maximum of the likelihood slightly off the truth (< 0.01°).
    let full = solve_ours(&d.setup, &obs, &OursConfig { selection: Some(Default::default()), ..cfg }).unwrap();
    let ef = pose_errors(&full.pose, &d.truth);
    assert!(ef.translation_m < 1e-4 && ef.rotation_rad < 1e-4, "ours with the selection stage {ef:?}");
    assert!(full.selection.is_some_and(|s| s.left_out >= n / 10), "{:?}", full.selection);
    assert!(ep.translation_m > 100.0 * eo.translation_m, "paper {ep:?} vs ours {eo:?}");
    assert!(
        o.residuals.inliers <= n - n / 10 && o.residuals.inliers >= n - n / 10 - 2,
        "{} of {n}",
        o.residuals.inliers
    );
}

/// The residual of `o` with frame perturbations `δ` applied, the slow way (for checking the
/// analytic Jacobians).
fn perturbed_residual(set: &PreparedSet, o: &Prepared, truth: &Isometry3<f64>, delta: &[f64; 18]) -> Vector2<f64> {
    let e = |k: usize| {
        se3_exp(
            &Vector3::new(delta[k], delta[k + 1], delta[k + 2]),
            &Vector3::new(delta[k + 3], delta[k + 4], delta[k + 5]),
        )
    };
    let cam = o.ecm_tip * e(0) * set.hand_eye;
    let f2 = o.psm_f2 * e(6);
    let f3 = f2 * Isometry3::translation(0.0, 0.0, o.insertion_m) * e(12);
    let p = cam.inverse() * (truth * Point3::from(f3.translation.vector));
    let dir = cam.rotation.inverse() * (truth.rotation * (f3.rotation * Vector3::z()));
    let l = set.k_inv_t * p.coords.cross(&dir);
    Vector2::from_fn(|j, _| (l.x * o.px[j].x + l.y * o.px[j].y + l.z) / l.xy().norm())
}

#[test]
fn analytic_jacobians_match_finite_differences() {
    let d = data(2, 2, 0.0, NoiseUnits::Millimetre, 0);
    let set = prepare(&d.setup, &d.observations).unwrap();
    let r = d.truth.rotation.to_rotation_matrix().into_inner();
    let t = d.truth.translation.vector;
    let h = 1e-7;
    for o in set.obs.iter().step_by(7) {
        let g = noise_jacobian(&set, o, &r, &t);
        for k in 0..18 {
            let (mut a, mut b) = ([0.0; 18], [0.0; 18]);
            a[k] = h;
            b[k] = -h;
            let num =
                (perturbed_residual(&set, o, &d.truth, &a) - perturbed_residual(&set, o, &d.truth, &b)) / (2.0 * h);
            assert!(
                (num - g.column(k)).norm() < 1e-4 * (1.0 + num.norm()),
                "δ{k}: numeric {num} analytic {}",
                g.column(k)
            );
        }
        let (_, j) = residual_and_jacobian(&set, o, &r, &t);
        for k in 0..6 {
            let mut dv = nalgebra::Vector6::zeros();
            dv[k] = h;
            let step = |s: f64| {
                let tt = t + dv.fixed_rows::<3>(0) * s;
                let rr = Rotation3::new(dv.fixed_rows::<3>(3) * s).into_inner() * r;
                residual_and_jacobian(&set, o, &rr, &tt).0
            };
            let num = (step(1.0) - step(-1.0)) / (2.0 * h);
            assert!((num - j.column(k)).norm() < 1e-4 * (1.0 + num.norm()), "param {k}: {num} vs {}", j.column(k));
        }
    }
}

#[test]
fn crb_scales_with_noise_and_shrinks_with_data() {
    let small = data(2, 3, 0.0, NoiseUnits::Millimetre, 0);
    let big = data(3, 3, 0.0, NoiseUnits::Millimetre, 0);
    let noise = |s: f64| KinematicNoise { rot_rad: s, trans_m: s * 1e-3, pixel_px: 0.0 };
    let a = cramer_rao_bound(&small.setup, &small.observations, &small.truth, &noise(0.01)).unwrap();
    let b = cramer_rao_bound(&small.setup, &small.observations, &small.truth, &noise(0.02)).unwrap();
    let c = cramer_rao_bound(&big.setup, &big.observations, &big.truth, &noise(0.01)).unwrap();
    assert!((b.translation_rms_m / a.translation_rms_m - 2.0).abs() < 1e-9);
    assert!((b.rotation_rms_rad / a.rotation_rms_rad - 2.0).abs() < 1e-9);
    assert!(c.translation_rms_m < a.translation_rms_m && c.rotation_rms_rad < a.rotation_rms_rad);
    assert!(cramer_rao_bound(&small.setup, &small.observations, &small.truth, &noise(0.0)).is_err());
}

#[test]
fn ours_covariance_is_consistent_with_the_crb() {
    // Millimetre reading: ours' covariance estimate agrees with the bound within a factor 2.
    let d = data(3, 3, 0.01, NoiseUnits::Millimetre, 5);
    let o = solve_ours(&d.setup, &d.observations, &OursConfig { noise: d.noise, ..OursConfig::default() }).unwrap();
    let clean = data(3, 3, 0.0, NoiseUnits::Millimetre, 0);
    let crb = cramer_rao_bound(&clean.setup, &clean.observations, &clean.truth, &d.noise.unwrap()).unwrap();
    let cov_t = (o.covariance[(0, 0)] + o.covariance[(1, 1)] + o.covariance[(2, 2)]).sqrt();
    let ratio = cov_t / crb.translation_rms_m;
    assert!((0.5..2.0).contains(&ratio), "covariance/CRB = {ratio}");
    assert!(o.covariance.symmetric_eigen().eigenvalues.iter().all(|v| *v > 0.0));
    assert!((0.7..1.5).contains(&o.scale), "whitened residual scale {}", o.scale);
}

#[test]
fn observations_feed_from_any_two_points_of_the_line() {
    // Moving a line point along the line does not change either pipeline's answer.
    let d = data(2, 2, 0.01, NoiseUnits::Millimetre, 2);
    let moved: Vec<Observation> = d
        .observations
        .iter()
        .map(|o| {
            let (a, b) = (Vector2::from(o.line_px[0]), Vector2::from(o.line_px[1]));
            let c = a + (b - a) * 0.5;
            Observation { line_px: [a.into(), c.into()], ..*o }
        })
        .collect();
    let p1 = solve_paper(&d.setup, &d.observations, &PaperConfig::default()).unwrap();
    let p2 = solve_paper(&d.setup, &moved, &PaperConfig::default()).unwrap();
    assert!((p1.pose.translation.vector - p2.pose.translation.vector).norm() < 1e-9);
}

#[test]
fn border_guard_removes_the_selection_bias_of_out_of_view_drops() {
    // Metre reading (10 mm per frame): observations near the image border were kept only when
    // their noise pushed the tip inward. The guard refits on tips predicted well inside.
    let (mut with, mut without) = (0.0, 0.0);
    for seed in 0..3 {
        let d = data(3, 3, 0.01, NoiseUnits::Metre, 100 + seed);
        // The guard alone (without the selection-aware stage, tested in calib_selection.rs).
        let cfg = OursConfig { noise: d.noise, selection: None, ..OursConfig::default() };
        let on = solve_ours(&d.setup, &d.observations, &cfg).unwrap();
        let off = solve_ours(&d.setup, &d.observations, &OursConfig { border_guard_sigmas: 0.0, ..cfg }).unwrap();
        assert!(on.guard_kept < d.observations.len() && off.guard_kept == d.observations.len());
        with += pose_errors(&on.pose, &d.truth).translation_rel;
        without += pose_errors(&off.pose, &d.truth).translation_rel;
    }
    assert!(with < 0.6 * without, "mean e_t with guard {} vs without {}", with / 3.0, without / 3.0);
}

/// The same poses seen by the right eye of a stereo endoscope (5 mm baseline): noise-free
/// right-eye lines are recovered exactly once the setup knows the right eye, refused with a
/// typed error when it does not, and a set mixing both eyes is recovered exactly too.
#[test]
fn right_eye_observations_use_the_stereo_transform() {
    use estimator::calib::Eye;
    use estimator::calib::rcm_arms::{camera_pose, psm_axis};
    let d = data(3, 3, 0.0, NoiseUnits::Millimetre, 3);
    let right = Isometry3::translation(0.005, 0.0, 0.0);
    let mut setup = d.setup;
    setup.right_eye = Some(right);
    let geometry = CalibGeometry::default();
    let right_obs: Vec<Observation> = d
        .observations
        .iter()
        .filter_map(|o| {
            let cam = camera_pose(&o.ecm_joints, &setup.hand_eye) * right;
            let m = d.truth.rotation * psm_axis(&o.psm_joints);
            let tip = d.truth.translation.vector + m * o.psm_joints[2];
            let [a, b] = sim::calib::observe_shaft(&geometry, &cam, &tip, &-m, 0.1)?;
            Some(Observation { line_px: [a.into(), b.into()], eye: Eye::Right, ..*o })
        })
        .collect();
    assert!(right_obs.len() > 20, "{} right-eye lines", right_obs.len());
    // A right-eye line is not a left-eye line: treated as left, the data do not fit.
    let as_left: Vec<Observation> = right_obs.iter().map(|o| Observation { eye: Eye::Left, ..*o }).collect();
    let wrong = solve_ours(&setup, &as_left, &OursConfig::default()).map(|r| pose_errors(&r.pose, &d.truth));
    assert!(wrong.as_ref().map_or(true, |e| e.translation_m > 1e-4), "{wrong:?}");
    let o = solve_ours(&setup, &right_obs, &OursConfig::default()).unwrap();
    let e = pose_errors(&o.pose, &d.truth);
    assert!(e.translation_m < 1e-9 && e.rotation_rad < 1e-9, "ours, right eye: {e:?}");
    let p = solve_paper(&setup, &right_obs, &PaperConfig::default()).unwrap();
    let e = pose_errors(&p.pose, &d.truth);
    assert!(e.translation_m < 1e-9 && e.rotation_rad < 1e-9, "paper, right eye: {e:?}");
    let both: Vec<Observation> = d.observations.iter().chain(right_obs.iter()).copied().collect();
    let o = solve_ours(&setup, &both, &OursConfig::default()).unwrap();
    let e = pose_errors(&o.pose, &d.truth);
    assert!(e.translation_m < 1e-9 && e.rotation_rad < 1e-9, "ours, both eyes: {e:?}");
    let mono = d.setup;
    assert_eq!(
        solve_ours(&mono, &right_obs, &OursConfig::default()).unwrap_err(),
        OursError::Prepare(PrepareError::NoRightEye { index: 0 })
    );
}

#[test]
fn cost_only_residual_and_shared_eq10_matrices_are_bit_identical() {
    use estimator::calib::paper::{eq10_symmetric, refine_quaternion_sym};
    use estimator::calib::residual::residual;
    let d = data(3, 3, 0.01, NoiseUnits::Metre, 3);
    let set = prepare(&d.setup, &d.observations).unwrap();
    let r =
        Rotation3::from_euler_angles(0.1, -0.2, 0.3).into_inner() * d.truth.rotation.to_rotation_matrix().into_inner();
    let t = d.truth.translation.vector + Vector3::new(0.01, -0.02, 0.005);
    for o in &set.obs {
        assert_eq!(residual(&set, o, &r, &t), residual_and_jacobian(&set, o, &r, &t).0);
    }
    let sym = eq10_symmetric(&set);
    for q0 in [Vector4::new(1.0, 0.0, 0.0, 0.0), Vector4::new(0.3, -0.5, 0.2, 0.7)] {
        let (a, ca, ia) = refine_quaternion(&set, &q0);
        let (b, cb, ib) = refine_quaternion_sym(&sym, &q0);
        assert_eq!((a, ca, ia), (b, cb, ib));
    }
}

/// Starts that enter an already refined candidate's basin are merged into it: a user start at
/// the result's own rotation is refined first and the linear start merges into it (or the
/// reverse); either way the pose is the converged one, within a small fraction of its standard
/// deviation of the solve without that start.
#[test]
fn merged_starts_give_the_converged_pose() {
    for (units, seed) in [(NoiseUnits::Millimetre, 11), (NoiseUnits::Metre, 12)] {
        let d = data(3, 3, 0.01, units, seed);
        let cfg = OursConfig { noise: d.noise, selection: None, ..OursConfig::default() };
        let a = solve_ours(&d.setup, &d.observations, &cfg).unwrap();
        let q = a.pose.rotation;
        let with_start = OursConfig { initial_quaternion: Some([q.w, q.i, q.j, q.k]), ..cfg };
        let b = solve_ours(&d.setup, &d.observations, &with_start).unwrap();
        let mut dv = SVector::<f64, 6>::zeros();
        dv.fixed_rows_mut::<3>(0).copy_from(&(b.pose.translation.vector - a.pose.translation.vector));
        dv.fixed_rows_mut::<3>(3).copy_from(&(b.pose.rotation * a.pose.rotation.inverse()).scaled_axis());
        let sigmas = dv.dot(&(a.covariance.try_inverse().unwrap() * dv)).sqrt();
        assert!(sigmas < 0.05, "{units:?}: {sigmas} standard deviations apart");
    }
}

/// A large dataset's candidates are searched on a subsample spread over it
/// (`OursConfig::search_observations`); the chosen basin is refined and judged on all
/// observations, so the answer is the full search's, to a small fraction of its standard
/// deviation. A small dataset is searched on all of it.
#[test]
fn a_large_dataset_is_searched_on_a_subsample_with_the_full_searchs_answer() {
    for units in [NoiseUnits::Millimetre, NoiseUnits::Metre] {
        let d = data(3, 4, 0.01, units, 7);
        let obs = &d.observations[..729];
        let cfg = OursConfig { noise: d.noise, ..OursConfig::default() };
        let n = cfg.search_observations.expect("on by default");
        let sub = solve_ours(&d.setup, obs, &cfg).unwrap();
        let all = solve_ours(&d.setup, obs, &OursConfig { search_observations: None, ..cfg }).unwrap();
        assert_eq!(all.searched_on, 729);
        // The golden-ratio subsample keeps n of the 729, to within a few.
        assert!(sub.searched_on.abs_diff(n) <= 3 && sub.searched_on < 729, "{} of {n}", sub.searched_on);
        let sd_t = (all.covariance[(0, 0)] + all.covariance[(1, 1)] + all.covariance[(2, 2)]).sqrt();
        let sd_r = (all.covariance[(3, 3)] + all.covariance[(4, 4)] + all.covariance[(5, 5)]).sqrt();
        let dt = (sub.pose.translation.vector - all.pose.translation.vector).norm();
        let dr = sub.pose.rotation.angle_to(&all.pose.rotation);
        assert!(dt < 0.05 * sd_t && dr < 0.05 * sd_r, "{units:?}: {dt} m ({sd_t}), {dr} rad ({sd_r})");
        // The runner-up is judged on all observations: a distinct, far less likely solution.
        assert!(sub.log_likelihood_ratio > 100.0 * DEFAULT_MIN_LOG_LIKELIHOOD_RATIO, "{}", sub.log_likelihood_ratio);
        assert!(sub.alternative.rotation.angle_to(&sub.pose.rotation) > 0.17);
        // The default searches from the cover of rotations every time, on the subsample too.
        assert!(sub.cover_searched && all.cover_searched, "scale {}", sub.scale);
    }
    let d = data(2, 3, 0.01, NoiseUnits::Millimetre, 7);
    let cfg = OursConfig { noise: d.noise, ..OursConfig::default() };
    assert!(d.observations.len() < 2 * cfg.search_observations.unwrap());
    let r = solve_ours(&d.setup, &d.observations, &cfg).unwrap();
    assert_eq!(r.searched_on, d.observations.len());
}

/// A subset of a prepared set counts its own views, tool orientations and pencil ratio (the
/// subsample search relies on them to fall back to all observations).
#[test]
fn a_subset_counts_its_own_views_and_orientations() {
    let d = data(3, 3, 0.01, NoiseUnits::Millimetre, 7);
    let set = prepare(&d.setup, &d.observations).unwrap();
    assert_eq!((set.views, set.orientations), (2, 3));
    let o0 = set.obs[0].o_ec;
    let one_view: Vec<Prepared> = set.obs.iter().filter(|o| (o.o_ec - o0).norm() < 1e-9).copied().collect();
    assert!(!one_view.is_empty() && one_view.len() < set.obs.len());
    let sub = set.with_observations(one_view);
    assert_eq!(sub.views, 1);
    let m0 = set.obs[0].m_t;
    let one_direction: Vec<Prepared> = set.obs.iter().filter(|o| o.m_t.cross(&m0).norm() < 1e-9).copied().collect();
    let sub = set.with_observations(one_direction);
    assert_eq!(sub.orientations, 1);
    assert!(sub.pencil_ratio < set.pencil_ratio, "{} {}", sub.pencil_ratio, set.pencil_ratio);
    // The full set's own observations give its own figures.
    let same = set.with_observations(set.obs.clone());
    assert_eq!((same.views, same.orientations, same.pencil_ratio), (set.views, set.orientations, set.pencil_ratio));
}
