//! Issue 19: one observation for both arm kinds. The same simulated motion written twice:
//! as the paper's RCM arm (the tool line through robot 2's RCM, the origin of `{t}`) and as
//! comanip's Achilles-type arm (the line through the fulcrum, known in the arm's base `{b}`,
//! along the instrument axis). Both must give the same calibration, up to the change of frame.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use estimator::calib::crb::cramer_rao_bound;
use estimator::calib::ours::{OursConfig, solve_ours};
use estimator::calib::paper::{PaperConfig, solve_paper};
use estimator::calib::prepare::{Prepared, PreparedSet, prepare};
use estimator::calib::rcm_arms::{psm_axis, se3_exp};
use estimator::calib::residual::{noise_jacobian, residual_and_jacobian};
use estimator::calib::{Observation, pose_errors};
use nalgebra::{Isometry3, Point3, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3};
use sim::calib::{CalibDataset, CalibGeometry, CalibProtocol, NoiseUnits, generate_calibration};

fn data(n_e: usize, n_t: usize, sigma: f64, units: NoiseUnits, seed: u64) -> CalibDataset {
    let p = CalibProtocol { geometry: CalibGeometry::default(), n_e, n_t, sigma, units, pixel_sigma_px: 0.0, seed };
    generate_calibration(&p).unwrap()
}

/// Where robot 2's RCM (the trocar) sits in the Achilles arm's base `{b}`: `T_b_t`, a
/// placement of the order of the real arm's (the trocar 0.3-0.4 m from the base origin).
fn trocar_in_base() -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(0.12, -0.25, 0.31), UnitQuaternion::from_euler_angles(0.3, -0.5, 1.1))
}

/// The dataset's observations as the Achilles arm would give them: the line through the
/// fulcrum `T_b_t · 0` along `R_b_t m(θ2)`, the tip at the same distance from it.
fn as_achilles(obs: &[Observation], b_t: &Isometry3<f64>) -> Vec<Observation> {
    obs.iter()
        .map(|o| {
            let axis = b_t.rotation * psm_axis(&o.psm_joints);
            Observation::from_tool_line(
                o.ecm_joints,
                b_t.translation.vector.into(),
                axis.into(),
                o.psm_joints[2],
                o.line_px,
                o.eye,
            )
            .unwrap()
        })
        .collect()
}

#[test]
fn from_tool_line_inverts_the_rcm_axis_and_refuses_a_zero_axis() {
    let q = [0.2, -0.3, 0.11];
    let m = psm_axis(&q);
    let o = Observation::from_tool_line(
        [0.0; 4],
        [0.0; 3],
        (m * 3.0).into(),
        0.11,
        [[0.0, 0.0], [1.0, 1.0]],
        Default::default(),
    )
    .unwrap();
    assert!((psm_axis(&o.psm_joints) - m).norm() < 1e-12);
    assert!((o.psm_joints[0] - q[0]).abs() < 1e-12 && (o.psm_joints[1] - q[1]).abs() < 1e-12);
    let bad = |a: [f64; 3]| {
        Observation::from_tool_line([0.0; 4], [0.0; 3], a, 0.1, [[0.0, 0.0], [1.0, 1.0]], Default::default())
    };
    assert!(bad([0.0; 3]).is_none());
    assert!(bad([f64::NAN, 0.0, 1.0]).is_none());
}

#[test]
fn noiseless_achilles_form_is_recovered_exactly_by_both_pipelines() {
    let d = data(2, 3, 0.0, NoiseUnits::Millimetre, 0);
    let b_t = trocar_in_base();
    let obs = as_achilles(&d.observations, &b_t);
    let truth_b = d.truth * b_t.inverse();
    let p = solve_paper(&d.setup, &obs, &PaperConfig::default()).unwrap();
    let e = pose_errors(&p.pose, &truth_b);
    assert!(e.translation_m < 1e-8 && e.rotation_rad < 1e-8, "paper {e:?}");
    let o = solve_ours(&d.setup, &obs, &OursConfig::default()).unwrap();
    let e = pose_errors(&o.pose, &truth_b);
    assert!(e.translation_m < 1e-8 && e.rotation_rad < 1e-8, "ours {e:?}");
}

/// The residual of `o` with frame perturbations `δ`, the slow way: the line frame (at the
/// line's point) and the tip frame perturbed.
fn perturbed_residual(set: &PreparedSet, o: &Prepared, truth: &Isometry3<f64>, delta: &[f64; 18]) -> Vector2<f64> {
    let e = |k: usize| {
        se3_exp(
            &Vector3::new(delta[k], delta[k + 1], delta[k + 2]),
            &Vector3::new(delta[k + 3], delta[k + 4], delta[k + 5]),
        )
    };
    let cam = o.ecm_tip * e(0) * set.hand_eye;
    let f2 = Isometry3::from_parts(Translation3::from(o.p_t), UnitQuaternion::identity()) * o.psm_f2 * e(6);
    let f3 = f2 * Isometry3::translation(0.0, 0.0, o.insertion_m) * e(12);
    let p = cam.inverse() * (truth * Point3::from(f3.translation.vector));
    let dir = cam.rotation.inverse() * (truth.rotation * (f3.rotation * Vector3::z()));
    let l = set.k_inv_t * p.coords.cross(&dir);
    Vector2::from_fn(|j, _| (l.x * o.px[j].x + l.y * o.px[j].y + l.z) / l.xy().norm())
}

#[test]
fn analytic_jacobians_match_finite_differences_with_a_point_off_the_origin() {
    let d = data(2, 2, 0.0, NoiseUnits::Millimetre, 0);
    let b_t = trocar_in_base();
    let obs = as_achilles(&d.observations, &b_t);
    let truth = d.truth * b_t.inverse();
    let set = prepare(&d.setup, &obs).unwrap();
    assert!(set.offset_points);
    let r = truth.rotation.to_rotation_matrix().into_inner();
    let t = truth.translation.vector;
    let h = 1e-7;
    for o in set.obs.iter().step_by(5) {
        let g = noise_jacobian(&set, o, &r, &t);
        for k in 0..18 {
            let (mut a, mut b) = ([0.0; 18], [0.0; 18]);
            a[k] = h;
            b[k] = -h;
            let num = (perturbed_residual(&set, o, &truth, &a) - perturbed_residual(&set, o, &truth, &b)) / (2.0 * h);
            assert!((num - g.column(k)).norm() < 1e-4 * (1.0 + num.norm()), "δ{k}: {num} vs {}", g.column(k));
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

/// Errors of a `T_e_b` estimate at the fulcrum (where the data are) and at the base origin.
fn errors_b(est: &Isometry3<f64>, truth: &Isometry3<f64>, fulcrum_b: &Vector3<f64>) -> (f64, f64, f64) {
    let at = |p: &Isometry3<f64>| p * Point3::from(*fulcrum_b);
    let e = pose_errors(est, truth);
    ((at(est) - at(truth)).norm(), e.translation_m, e.rotation_rad)
}

#[test]
fn same_motion_same_precision_for_both_arm_kinds() {
    // Metre reading (10 mm / 0.57° per frame at σ = 0.01 would be the hard case; 0.005 here).
    let b_t = trocar_in_base();
    let fulcrum_b = b_t.translation.vector;
    for (units, sigma, seed) in [(NoiseUnits::Millimetre, 0.01, 3), (NoiseUnits::Metre, 0.005, 4)] {
        let d = data(3, 3, sigma, units, seed);
        let cfg = OursConfig { noise: d.noise, ..OursConfig::default() };
        let rcm = solve_ours(&d.setup, &d.observations, &cfg).unwrap();
        let obs = as_achilles(&d.observations, &b_t);
        let ach = solve_ours(&d.setup, &obs, &cfg).unwrap();
        let truth_b = d.truth * b_t.inverse();
        let e_rcm = pose_errors(&rcm.pose, &d.truth);
        let (e_f, _, e_r) = errors_b(&ach.pose, &truth_b, &fulcrum_b);
        // The same estimate up to the change of frame: equal errors at the fulcrum. Not to the
        // micrometre: the two kinds start the lines' own fit differently (Eq. 5, Eq. 5 given
        // the rotation) and the shaft-position terms' objective has stationary points a few
        // micrometres apart; within a tenth of the error.
        let close = |a: f64, b: f64| (a - b).abs() <= 0.1 * a.max(b);
        assert!(close(e_f, e_rcm.translation_m), "{units:?}: fulcrum {e_f} vs RCM {}", e_rcm.translation_m);
        assert!(close(e_r, e_rcm.rotation_rad), "{units:?}: rotation {e_r} vs {}", e_rcm.rotation_rad);
        // The bound too: the fulcrum's covariance J Σ Jᵀ equals the RCM's.
        let noise = d.noise.unwrap();
        let c_rcm = cramer_rao_bound(&d.setup, &d.observations, &d.truth, &noise).unwrap();
        let c_ach = cramer_rao_bound(&d.setup, &obs, &truth_b, &noise).unwrap();
        assert!((c_rcm.rotation_rms_rad / c_ach.rotation_rms_rad - 1.0).abs() < 1e-6);
        let at_fulcrum = fulcrum_covariance(&c_ach.covariance, &truth_b, &fulcrum_b);
        assert!((at_fulcrum.sqrt() / c_rcm.translation_rms_m - 1.0).abs() < 1e-6, "{at_fulcrum} vs {c_rcm:?}");
    }
}

/// `tr` of the covariance (m²) of the point `p_b` mapped by a pose with covariance `cov`
/// (left increments in `{e}`): `p_e = R p + t`, `∂p_e/∂(t, δφ) = [I, −[R p]×]`.
fn fulcrum_covariance(cov: &nalgebra::Matrix6<f64>, pose: &Isometry3<f64>, p_b: &Vector3<f64>) -> f64 {
    let rp = pose.rotation * p_b;
    let mut j = nalgebra::SMatrix::<f64, 3, 6>::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&nalgebra::Matrix3::identity());
    j.fixed_view_mut::<3, 3>(0, 3).copy_from(&-rp.cross_matrix());
    (j * cov * j.transpose()).trace()
}

/// The measurement behind docs/calibration.md's "live" section, first table:
/// `cargo test -p integration-tests --test calib_tool_line -- --ignored --nocapture`.
#[test]
#[ignore = "measurement (30 trials per condition), run by hand for docs/calibration.md"]
fn measure_both_arm_kinds_on_the_same_motion() {
    let b_t = trocar_in_base();
    let fulcrum_b = b_t.translation.vector;
    println!(
        "| reading | σ | RCM arm: RMS t mm / R ° | Achilles arm: RMS at fulcrum mm / R ° | Achilles: RMS base origin mm | CRB RCM t mm / R ° | CRB Achilles at fulcrum mm / R ° |"
    );
    println!("|---|---|---|---|---|---|---|");
    for (units, sigma) in [(NoiseUnits::Millimetre, 0.01), (NoiseUnits::Metre, 0.005)] {
        let (mut s_rt, mut s_rr, mut s_af, mut s_ar, mut s_ab, mut n) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let mut crb = (0.0, 0.0, 0.0, 0.0);
        for k in 0..30 {
            let d = data(3, 3, sigma, units, 1000 + k);
            let cfg = OursConfig { noise: d.noise, ..OursConfig::default() };
            let obs = as_achilles(&d.observations, &b_t);
            let (Ok(rcm), Ok(ach)) = (solve_ours(&d.setup, &d.observations, &cfg), solve_ours(&d.setup, &obs, &cfg))
            else {
                continue;
            };
            let truth_b = d.truth * b_t.inverse();
            let e = pose_errors(&rcm.pose, &d.truth);
            let (ef, eb, er) = errors_b(&ach.pose, &truth_b, &fulcrum_b);
            s_rt += e.translation_m.powi(2);
            s_rr += e.rotation_rad.powi(2);
            s_af += ef.powi(2);
            s_ab += eb.powi(2);
            s_ar += er.powi(2);
            n += 1.0;
            if k == 0 {
                let clean = data(3, 3, 0.0, units, 0);
                let noise = d.noise.unwrap();
                let c_r = cramer_rao_bound(&clean.setup, &clean.observations, &clean.truth, &noise).unwrap();
                let obs0 = as_achilles(&clean.observations, &b_t);
                let c_a = cramer_rao_bound(&clean.setup, &obs0, &(clean.truth * b_t.inverse()), &noise).unwrap();
                let f = fulcrum_covariance(&c_a.covariance, &(clean.truth * b_t.inverse()), &fulcrum_b).sqrt();
                crb = (c_r.translation_rms_m, c_r.rotation_rms_rad, f, c_a.rotation_rms_rad);
            }
        }
        let rms = |s: f64| (s / n).sqrt();
        println!(
            "| {units:?} | {sigma} | {:.3} / {:.4} | {:.3} / {:.4} | {:.2} | {:.3} / {:.4} | {:.3} / {:.4} |",
            rms(s_rt) * 1e3,
            rms(s_rr).to_degrees(),
            rms(s_af) * 1e3,
            rms(s_ar).to_degrees(),
            rms(s_ab) * 1e3,
            crb.0 * 1e3,
            crb.1.to_degrees(),
            crb.2 * 1e3,
            crb.3.to_degrees()
        );
    }
}
