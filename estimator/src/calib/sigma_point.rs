//! Sigma-point (second-order) propagation of the 18 frame perturbations to an observation's
//! two line residuals: their mean and covariance, for when the first-order model
//! ([`super::residual::residual_covariance`], mean zero) is not accurate (10 mm per frame with
//! the tool tip a few centimetres from the camera).
//!
//! The transform is the second-order divided-difference one (Nørgaard, Poulsen and Ravn,
//! "New developments in state estimation for nonlinear systems", Automatica 2000) — a
//! per-axis unscented transform: with independent perturbations `δ_j ~ N(0, σ_j²)`, the
//! function is evaluated at the centre and at `±h σ_j` along each axis, `h = √3` (so each
//! axis' fourth moment is the Gaussian's), 37 evaluations for 18 perturbations. With
//! `a_j = (f(+) − f(−)) / (2h)` and `b_j = (f(+) + f(−) − 2 f(0)) / (2h²)` (first and second
//! differences per unit σ_j):
//! - mean `f(0) + Σ_j b_j` (exact for a quadratic without cross terms; the cross terms do not
//!   shift the mean of independent perturbations);
//! - covariance `Σ_j a_j a_jᵀ + 2 b_j b_jᵀ` (exact for a quadratic without cross terms:
//!   `Var(a x + b x²) = a² + 2b²` for `x ~ N(0, 1)`).
//!
//! A linear function gives mean `f(0)` and the first-order covariance exactly.

use nalgebra::{Isometry3, Matrix2, Matrix3, SVector, Vector2, Vector3};

use super::KinematicNoise;
use super::prepare::{Prepared, PreparedSet};
use super::rcm_arms::se3_exp;

/// The per-axis step in standard deviations: `√3` (the Gaussian's fourth moment).
pub const SIGMA_POINT_STEP: f64 = 1.732_050_807_568_877_2;

/// Mean and covariance of `f(δ)` for independent `δ_j ~ N(0, variances_j)` (18 perturbations;
/// any units, `f` in its own units) by the per-axis sigma-point transform (module docs).
/// `None` when `f` is not finite at a sigma point.
pub fn second_order_moments<const R: usize>(
    variances: &[f64; 18],
    f: impl Fn(&SVector<f64, 18>) -> Option<SVector<f64, R>>,
) -> Option<(SVector<f64, R>, nalgebra::SMatrix<f64, R, R>)> {
    let f0 = f(&SVector::zeros())?;
    let mut mean = f0;
    let mut cov = nalgebra::SMatrix::<f64, R, R>::zeros();
    let h = SIGMA_POINT_STEP;
    for (j, v) in variances.iter().enumerate() {
        if *v <= 0.0 {
            continue;
        }
        let sd = v.sqrt();
        let mut d = SVector::<f64, 18>::zeros();
        d[j] = h * sd;
        let fp = f(&d)?;
        let fm = f(&-d)?;
        let a = (fp - fm) / (2.0 * h);
        let b = (fp + fm - f0 * 2.0) / (2.0 * h * h);
        mean += b;
        cov += a * a.transpose() + b * b.transpose() * 2.0;
    }
    (mean.iter().chain(cov.iter()).all(|v| v.is_finite())).then_some((mean, cov))
}

/// The residual pair (pixels) of observation `o` at the model pose `(R, t)` (`T_e_t`) when the
/// actual frames are perturbed by `δ = (δ_ECM, δ_PSM2, δ_PSM3)` (each `(ρ m, φ rad)`, the
/// simulation protocol's `T·exp(δ^)`): each observed line point moved, across the model line,
/// onto the actual line: the signed distance, along the model line's normal, at which the
/// actual line crosses the normal through the point's foot on the model line. Zero at
/// `δ = 0`; to first order `−G δ` with `G` the noise Jacobian
/// ([`super::residual::noise_jacobian`]). `None` when the actual line degenerates (seen
/// end-on, or parallel to the normal).
pub fn perturbed_residual(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    delta: &SVector<f64, 18>,
) -> Option<Vector2<f64>> {
    let part = |k: usize| {
        se3_exp(
            &Vector3::new(delta[6 * k], delta[6 * k + 1], delta[6 * k + 2]),
            &Vector3::new(delta[6 * k + 3], delta[6 * k + 4], delta[6 * k + 5]),
        )
    };
    let cam_nominal =
        Isometry3::from_parts(nalgebra::Translation3::from(o.o_ec), nalgebra::UnitQuaternion::from_matrix(&o.r_ec));
    // This eye's hand-eye transform, from the prepared camera pose.
    let eye = o.ecm_tip.inverse() * cam_nominal;
    let cam = o.ecm_tip * part(0) * eye;
    // The tool: F2·exp(δa)·Trans(d ẑ)·exp(δb), F2 at the line's point.
    let f2 = Isometry3::from_parts(nalgebra::Translation3::from(o.p_t), o.psm_f2.rotation);
    let f3 = f2 * part(1) * Isometry3::translation(0.0, 0.0, o.insertion_m) * part(2);
    let pose = Isometry3::from_parts(nalgebra::Translation3::from(*t), nalgebra::UnitQuaternion::from_matrix(r));
    let to_cam = cam.inverse() * pose;
    let p_c = to_cam * nalgebra::Point3::from(f3.translation.vector);
    let d_c = to_cam.rotation * (f3.rotation * Vector3::z());
    let actual = set.k_inv_t * p_c.coords.cross(&d_c);
    // The model line (unperturbed).
    let rt = o.r_ec.transpose();
    let p0 = rt * (r * (o.p_t + o.m_t * o.insertion_m) + t - o.o_ec);
    let d0 = rt * (r * o.m_t);
    let model = set.k_inv_t * p0.cross(&d0);
    let n0 = Vector2::new(model.x, model.y);
    let s0 = n0.norm();
    if s0 < 1e-300 {
        return None;
    }
    let n0 = n0 / s0;
    let na = Vector2::new(actual.x, actual.y);
    let mut out = Vector2::zeros();
    for j in 0..2 {
        let p = o.px[j];
        let d_model = (model.x * p.x + model.y * p.y + model.z) / s0;
        // The foot of p on the model line, then along n0 to the actual line:
        // actual·(q + s n0) = 0 ⇒ s = −actual(q) / (na·n0).
        let q = p - n0 * d_model;
        let den = na.dot(&n0);
        if den.abs() < 1e-12 * na.norm() {
            return None;
        }
        out[j] = -(actual.x * q.x + actual.y * q.y + actual.z) / den;
    }
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// The residual pair's mean (pixels; zero under the first-order model) and covariance
/// (pixels², pixel noise included)
/// of observation `o` at `(R, t)` under `noise`, by the sigma-point transform (module docs).
/// `None` when the actual line degenerates at a sigma point.
pub fn residual_moments(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    noise: &KinematicNoise,
) -> Option<(Vector2<f64>, Matrix2<f64>)> {
    let (mean, cov) = second_order_moments(&noise.perturbation_variances(), |d| perturbed_residual(set, o, r, t, d))?;
    Some((mean, cov + Matrix2::identity() * (noise.pixel_px * noise.pixel_px)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{SMatrix, Vector2};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    fn variances() -> [f64; 18] {
        core::array::from_fn(|j| 0.01 * (1.0 + (j % 5) as f64) * (1.0 + (j % 2) as f64))
    }

    #[test]
    fn a_linear_function_gives_the_first_order_moments() {
        let g = SMatrix::<f64, 2, 18>::from_fn(|i, j| ((3 * i + 7 * j) % 11) as f64 - 5.0);
        let c = Vector2::new(0.3, -1.2);
        let (m, s) = second_order_moments(&variances(), |d| Some(c + g * d)).unwrap();
        let d = SMatrix::<f64, 18, 18>::from_diagonal(&SVector::from(variances()));
        assert!((m - c).norm() < 1e-12);
        assert!((s - g * d * g.transpose()).norm() < 1e-9 * s.norm());
    }

    #[test]
    fn a_nonlinear_function_matches_monte_carlo() {
        // Perspective-like: a ratio with a strongly varying denominator; a square and a sine.
        // (Cross products of two perturbations are not in the per-axis covariance: their
        // variance is fourth order, small where the first order is nearly right.)
        let v = variances();
        let f = |d: &SVector<f64, 18>| -> Option<Vector2<f64>> {
            Some(Vector2::new((1.0 + d[0]) / (1.0 + 0.5 * d[1] + 0.3 * d[2]), d[3] * d[3] + (0.4 * d[5]).sin()))
        };
        let (m, s) = second_order_moments(&v, f).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let n = 400_000;
        let (mut sm, mut ss) = (Vector2::zeros(), Matrix2::zeros());
        for _ in 0..n {
            let d = SVector::<f64, 18>::from_fn(|j, _| rng.sample::<f64, _>(StandardNormal) * v[j].sqrt());
            let y = f(&d).unwrap();
            sm += y;
            ss += y * y.transpose();
        }
        let mc_m = sm / n as f64;
        let mc_s = ss / n as f64 - mc_m * mc_m.transpose();
        // The first-order mean would be (1, 0): the ratio's mean is shifted by ≈ +0.0094.
        assert!((mc_m.x - 1.0) > 0.005, "{mc_m}");
        assert!((m.x - mc_m.x).abs() < 0.2 * (mc_m.x - 1.0), "{m} vs {mc_m}");
        // The square's mean: its variance, 0.08.
        assert!((mc_m.y - 0.08).abs() < 3e-3, "{mc_m}");
        assert!((m.y - mc_m.y).abs() < 3e-3, "{m} vs {mc_m}");
        for k in 0..2 {
            assert!((s[(k, k)] - mc_s[(k, k)]).abs() < 0.1 * mc_s[(k, k)], "{s} vs {mc_s}");
        }
    }

    #[test]
    fn not_finite_gives_none() {
        let r = second_order_moments::<1>(&variances(), |d| Some(SVector::<f64, 1>::new(1.0 / d[0])));
        assert!(r.is_none());
    }
}
