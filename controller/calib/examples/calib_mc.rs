//! Monte-Carlo check of the first-order noise model of the residuals (issue 20, metre
//! reading): per observation of one protocol dataset, draws the 18 frame perturbations many
//! times, re-observes the shaft, and compares the whitened residuals at the truth (whitened by
//! the first-order covariance at each draw's own line points) with N(0, I); then the bias
//! those mean residuals imply for the fit of all lines, `H⁻¹ Σ Jᵀ Σ⁻¹ E[r]`, in standard
//! deviations of the fit (`√(bᵀ H b)`). With `ut` as 6th argument the first-order covariance
//! is replaced by the sigma-point model (mean removed).
//!
//! `cargo run --release -p comanip-calib --example calib_mc -- <geometry seed> <index> [mm|m]
//! [sigma] [draws] [min_visible_px]` (tuning geometries only: 9000..9019).
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "diagnostic tool: a panic is a bug report")]

use estimator::calib::prepare::{prepare, prepare_unchecked};
use estimator::calib::rcm_arms::{ecm_frames, psm_frames, se3_exp};
use estimator::calib::residual::{residual, residual_and_jacobian, residual_covariance};
use estimator::calib::sigma_point::{perturbed_residual, residual_moments};
use estimator::calib::{Observation, SelectionRule};
use nalgebra::{Isometry3, Matrix2, Matrix6, SVector, Vector2, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use sim::calib::{CalibProtocol, NoiseUnits, generate_calibration, observe_shaft, random_geometry};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seed: u64 = a.get(1).map_or(9000, |s| s.parse().unwrap());
    let index: u64 = a.get(2).map_or(0, |s| s.parse().unwrap());
    let units = match a.get(3).map(String::as_str) {
        Some("mm") => NoiseUnits::Millimetre,
        _ => NoiseUnits::Metre,
    };
    let sigma: f64 = a.get(4).map_or(0.01, |s| s.parse().unwrap());
    let draws: usize = a.get(5).map_or(2000, |s| s.parse().unwrap());
    let min_vis: Option<f64> = a.get(6).map(|s| s.parse().unwrap());
    let mut geo = random_geometry(seed, index % 2 == 1).unwrap().geometry;
    if let Some(v) = min_vis {
        geo.selection = SelectionRule { min_visible_shaft_px: v, ..geo.selection };
    }
    let p = CalibProtocol { geometry: geo, n_e: 3, n_t: 3, sigma, units, pixel_sigma_px: 0.0, seed: 1000 };
    let d = generate_calibration(&p).unwrap();
    let set = prepare(&d.setup, &d.observations).unwrap();
    let noise = d.noise.unwrap();
    let rt = d.truth.rotation.to_rotation_matrix().into_inner();
    let tt = d.truth.translation.vector;
    let rho = units.metres();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let draw18 = |rng: &mut ChaCha8Rng| -> SVector<f64, 18> {
        SVector::<f64, 18>::from_fn(|j, _| {
            rng.sample::<f64, _>(StandardNormal) * sigma * if j % 6 < 3 { rho } else { 1.0 }
        })
    };
    let part = |d: &SVector<f64, 18>, k: usize| -> Isometry3<f64> {
        se3_exp(
            &Vector3::new(d[6 * k], d[6 * k + 1], d[6 * k + 2]),
            &Vector3::new(d[6 * k + 3], d[6 * k + 4], d[6 * k + 5]),
        )
    };
    let mut fn_err = Vec::new();
    let mut fn_bias = Vec::new();
    let mut s_fn = Vector6::zeros();
    let (mut h, mut s, mut s_ut) = (Matrix6::zeros(), Vector6::zeros(), Vector6::zeros());
    let mut ut_err = Vec::new();
    let mut zbias = Vec::new();
    let mut var_ratio = Vec::new();
    for (i, (ob, o)) in d.observations.iter().zip(&set.obs).enumerate() {
        // Nominal Jacobian and first-order covariance at the truth for the fit's information.
        let (_, j) = residual_and_jacobian(&set, o, &rt, &tt);
        let w = residual_covariance(&set, o, &rt, &tt, &noise).try_inverse().unwrap();
        h += j.transpose() * w * j;
        let f4 = ecm_frames(&ob.ecm_joints)[3];
        let fr = psm_frames(&ob.psm_joints);
        let (mut sum_r, mut sum_z, mut szz, mut kept) = (Vector2::zeros(), Vector2::zeros(), Matrix2::zeros(), 0usize);
        let mut sum_f = Vector2::zeros();
        for _ in 0..draws {
            let dd = draw18(&mut rng);
            sum_f += perturbed_residual(&set, o, &rt, &tt, &dd).unwrap_or_default();
            let (de, da, db) = (part(&dd, 0), part(&dd, 1), part(&dd, 2));
            let cam = f4 * de * geo.hand_eye;
            let f2 = fr[1] * da;
            let f3 = f2 * Isometry3::translation(0.0, 0.0, ob.psm_joints[2]) * db;
            let tip_e = geo.truth * nalgebra::Point3::from(f3.translation.vector);
            let back_e = geo.truth.rotation * (f3.rotation * -Vector3::z());
            let Some([pa, pb]) = observe_shaft(&geo, &cam, &tip_e.coords, &back_e, ob.psm_joints[2]) else { continue };
            let obs = Observation { line_px: [[pa.x, pa.y], [pb.x, pb.y]], ..*ob };
            let Ok(one) = prepare_unchecked(&d.setup, &[obs]) else { continue };
            let q = &one.obs[0];
            let r = residual(&one, q, &rt, &tt);
            let c = residual_covariance(&one, q, &rt, &tt, &noise);
            let Some(ch) = c.cholesky() else { continue };
            let z = ch.l().try_inverse().unwrap() * r;
            sum_r += r;
            sum_z += z;
            szz += z * z.transpose();
            kept += 1;
        }
        if kept < 10 {
            continue;
        }
        let n = kept as f64;
        let (mu, cu) = residual_moments(&set, o, &rt, &tt, &noise).unwrap();
        s_ut += j.transpose() * w * mu;
        let wl = residual_covariance(&set, o, &rt, &tt, &noise).cholesky().unwrap().l().try_inverse().unwrap();
        let mr = sum_r / n;
        // The sigma-point mean's error against Monte Carlo, in first-order sd units.
        ut_err.push((wl * (mu - mr)).norm());
        // The nonlinear residual without selection: Monte Carlo vs sigma points.
        let mf = sum_f / draws as f64;
        fn_err.push((wl * (mu - mf)).norm());
        fn_bias.push((wl * mf).norm());
        s_fn += j.transpose() * w * mf;
        let mz = sum_z / n;
        let cz = szz / n - mz * mz.transpose();
        zbias.push(mz.norm());
        var_ratio.push(cz.trace() / 2.0);
        s += j.transpose() * w * (sum_r / n);
        if i < 8 || std::env::var("ALL").is_ok() {
            let mu_w = wl * mu;
            let cu_w = wl * cu * wl.transpose();
            println!(
                "obs {i}: kept {kept}/{draws} whitened mean MC ({:+.3}, {:+.3}) UT ({:+.3}, {:+.3}) sd-units, whitened var diag MC ({:.2}, {:.2}) UT ({:.2}, {:.2})",
                mz.x,
                mz.y,
                mu_w.x,
                mu_w.y,
                cz[(0, 0)],
                cz[(1, 1)],
                cu_w[(0, 0)],
                cu_w[(1, 1)]
            );
        }
    }
    let med = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        (v[v.len() / 2], v[v.len() * 9 / 10], v[v.len() - 1])
    };
    let (bm, b90, bmax) = med(&mut zbias);
    let (vm, v90, vmax) = med(&mut var_ratio);
    let (em, e90, emax) = med(&mut ut_err);
    println!("sigma-point mean minus MC mean (first-order sd units): median {em:.3} p90 {e90:.3} max {emax:.3}");
    let b_ut = h.try_inverse().unwrap() * s_ut;
    println!(
        "bias predicted by the sigma-point means: {:.1} sd (t {:.2} mm, R {:.3} deg)",
        b_ut.dot(&(h * b_ut)).sqrt(),
        b_ut.fixed_rows::<3>(0).norm() * 1e3,
        b_ut.fixed_rows::<3>(3).norm().to_degrees()
    );
    let (fm, f90, fmax) = med(&mut fn_bias);
    let (gm, g90, gmax) = med(&mut fn_err);
    let b_fn = h.try_inverse().unwrap() * s_fn;
    println!(
        "without selection (nonlinearity only): |E z| MC median {fm:.3} p90 {f90:.3} max {fmax:.3}; sigma-point error median {gm:.3} p90 {g90:.3} max {gmax:.3}; implied fit bias {:.1} sd (t {:.2} mm, R {:.3} deg)",
        b_fn.dot(&(h * b_fn)).sqrt(),
        b_fn.fixed_rows::<3>(0).norm() * 1e3,
        b_fn.fixed_rows::<3>(3).norm().to_degrees()
    );
    let b = h.try_inverse().unwrap() * s;
    println!(
        "{seed} {units:?} σ={sigma}: {} observations; |E z| (sd units) median {bm:.3} p90 {b90:.3} max {bmax:.3}; var(z) median {vm:.2} p90 {v90:.2} max {vmax:.2}",
        set.obs.len()
    );
    println!(
        "implied bias of the fit of all lines: {:.1} sd of the fit (t {:.2} mm, R {:.3} deg); fit sd t {:.2} mm",
        b.dot(&(h * b)).sqrt(),
        b.fixed_rows::<3>(0).norm() * 1e3,
        b.fixed_rows::<3>(3).norm().to_degrees(),
        {
            let c = h.try_inverse().unwrap();
            (c[(0, 0)] + c[(1, 1)] + c[(2, 2)]).sqrt() * 1e3
        }
    );
}
