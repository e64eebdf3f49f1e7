//! The residual model shared by our pipeline, its selection-aware stage and the Cramér-Rao
//! bounds: the two image distances (pixels) of an observed tool line's end points to the
//! tool axis projected at a pose `(R, t)` of the tool arm's base in the endoscope arm's
//! frame `{e}`, their Jacobians w.r.t. the pose `(t m, δφ rad)` and w.r.t. the simulation
//! protocol's frame perturbations, their covariance under a kinematic noise model, and the
//! damped Gauss-Newton step. Layer: above [`super::prepare`], below [`super::ours`],
//! [`super::selection`] and [`super::crb`], which import it and never each other's
//! internals.

use nalgebra::{Matrix2, Matrix3, Matrix6, SMatrix, Vector2, Vector3, Vector6};

use super::KinematicNoise;
use super::prepare::{Prepared, PreparedSet};
use super::rcm_arms::skew;

/// 2×6 Jacobian of one observation's residual pair w.r.t. `(t, δφ)`.
pub type Jac6 = SMatrix<f64, 2, 6>;
/// 2×18 Jacobian of one observation's residual pair w.r.t. the frame perturbations
/// `(δ_ECM, δ_PSM2, δ_PSM3)`, each `(ρ m, φ rad)`.
pub type Jac18 = SMatrix<f64, 2, 18>;

fn dist_and_grad(l: &Vector3<f64>, u: &Vector2<f64>) -> (f64, nalgebra::RowVector3<f64>) {
    let s2 = l.x * l.x + l.y * l.y;
    let s = s2.sqrt();
    let lu = l.x * u.x + l.y * u.y + l.z;
    let r = lu / s;
    let g = nalgebra::RowVector3::new(u.x / s - lu * l.x / (s2 * s), u.y / s - lu * l.y / (s2 * s), 1.0 / s);
    (r, g)
}

/// The image line `l` (homogeneous, ideal pixels) of the tool axis of observation `o` at pose
/// `(R, t)`, from `a = R p + t − o_ec` (the line's point relative to the camera centre, metres,
/// `{e}`) and `Rm` (its direction, `{e}`): `l = K⁻ᵀ R_ecᵀ (a × Rm)` (a rotation commutes with
/// the cross product, so the point and direction need not be taken into the camera frame).
fn image_line(set: &PreparedSet, o: &Prepared, a: &Vector3<f64>, rm: &Vector3<f64>) -> Vector3<f64> {
    set.k_inv_t * o.r_ec.tr_mul(&a.cross(rm))
}

/// Residual pair (pixels) of observation `o` for pose `(R, t)` and its Jacobian w.r.t.
/// `(t, δφ)`.
///
/// With `n = a × Rm` (`a = R p + t − o_ec`, `{e}`) and each residual `r_j = g_j l`,
/// `l = K⁻ᵀ R_ecᵀ n`, the row is `vᵀ ∂n`, `v = R_ec K⁻¹ g_jᵀ`: `∂n/∂t = −[Rm]×` and, as
/// `R ← exp(δφ^) R` moves both `Rp` and `Rm`, `∂n/∂δφ = [Rm]×[Rp]× − [a]×[Rm]×`; so with
/// `c = v × Rm` the row is `(−c, c × Rp − (v × a) × Rm)`: cross products only.
pub fn residual_and_jacobian(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
) -> (Vector2<f64>, Jac6) {
    let rm = r * o.m_t;
    let rp = r * o.p_t;
    let a = rp + t - o.o_ec;
    let l = image_line(set, o, &a, &rm);
    let mut res = Vector2::zeros();
    let mut jac = Jac6::zeros();
    for j in 0..2 {
        let (rj, g) = dist_and_grad(&l, &o.px[j]);
        res[j] = rj;
        let v = o.r_ec * set.k_inv_t.tr_mul(&g.transpose());
        let c = v.cross(&rm);
        let dphi = c.cross(&rp) - v.cross(&a).cross(&rm);
        for k in 0..3 {
            jac[(j, k)] = -c[k];
            jac[(j, k + 3)] = dphi[k];
        }
    }
    (res, jac)
}

/// Residual pair (pixels) of observation `o` for pose `(R, t)`, without its Jacobian: the same
/// arithmetic as [`residual_and_jacobian`]'s residual (bit-identical), for cost evaluations.
pub fn residual(set: &PreparedSet, o: &Prepared, r: &Matrix3<f64>, t: &Vector3<f64>) -> Vector2<f64> {
    let rm = r * o.m_t;
    let rp = r * o.p_t;
    let l = image_line(set, o, &(rp + t - o.o_ec), &rm);
    let s = (l.x * l.x + l.y * l.y).sqrt();
    Vector2::new((l.x * o.px[0].x + l.y * o.px[0].y + l.z) / s, (l.x * o.px[1].x + l.y * o.px[1].y + l.z) / s)
}

/// Jacobian (pixels per metre / radian) of observation `o`'s residual pair w.r.t. the 18
/// frame perturbations of the simulation protocol at pose `(R, t)`: `δ_ECM` right-multiplied
/// on the ECM end effector, `δ_PSM2`, `δ_PSM3` on PSM frames 2 and 3, each `(ρ, φ)`.
pub fn noise_jacobian(set: &PreparedSet, o: &Prepared, r: &Matrix3<f64>, t: &Vector3<f64>) -> Jac18 {
    let rt = o.r_ec.transpose();
    let rm = r * o.m_t;
    let p_c = rt * (r * (o.p_t + o.m_t * o.insertion_m) + t - o.o_ec);
    let d_c = rt * rm;
    let (sp, sd) = (skew(&p_c), skew(&d_c));
    let mut dn = SMatrix::<f64, 3, 18>::zeros();
    // Camera: right perturbation δc = Ad(X⁻¹) δe in the camera frame.
    let mut dn_c = SMatrix::<f64, 3, 6>::zeros();
    dn_c.fixed_view_mut::<3, 3>(0, 0).copy_from(&sd);
    dn_c.fixed_view_mut::<3, 3>(0, 3).copy_from(&(sp * sd - sd * sp));
    let ad = &o.eye_inv_adjoint;
    dn.fixed_view_mut::<3, 6>(0, 0).copy_from(&(dn_c * *ad));
    // Tool: δP = R2(ρa + ρb − d[ẑ]×φa), δD = −R2[ẑ]×(φa + φb), mapped into the camera.
    let a = rt * r * o.r2;
    let z = skew(&Vector3::z());
    let d = o.insertion_m;
    // `(−x) y = −(x y)` exactly (rounding is symmetric): the shared products once.
    let sd_a = sd * a;
    let sp_a_z = sp * a * z;
    let dn_rho = -sd_a;
    let dn_phi_a = sd_a * z * d - sp_a_z;
    let dn_phi_b = -sp_a_z;
    dn.fixed_view_mut::<3, 3>(0, 6).copy_from(&dn_rho);
    dn.fixed_view_mut::<3, 3>(0, 9).copy_from(&dn_phi_a);
    dn.fixed_view_mut::<3, 3>(0, 12).copy_from(&dn_rho);
    dn.fixed_view_mut::<3, 3>(0, 15).copy_from(&dn_phi_b);
    let l = set.k_inv_t * p_c.cross(&d_c);
    let dl = set.k_inv_t * dn;
    let mut g = Jac18::zeros();
    for j in 0..2 {
        let (_, grad) = dist_and_grad(&l, &o.px[j]);
        g.set_row(j, &(grad * dl));
    }
    g
}

/// The 2×2 covariance (pixels²) of observation `o`'s residual pair under `noise` at `(R, t)`.
pub fn residual_covariance(
    set: &PreparedSet,
    o: &Prepared,
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    noise: &KinematicNoise,
) -> Matrix2<f64> {
    noise.propagate(&noise_jacobian(set, o, r, t))
}

/// The Levenberg-Marquardt step `−(H + λ diag H)⁻¹ g` in `(t m, δφ rad)`; `None` when the
/// damped matrix is not positive definite (raise `λ`).
pub fn damped_step(h: &Matrix6<f64>, g: &Vector6<f64>, lambda: f64) -> Option<Vector6<f64>> {
    let mut a = *h;
    for i in 0..6 {
        a[(i, i)] += lambda * h[(i, i)].max(1e-12);
    }
    a.cholesky().map(|ch| ch.solve(&-g))
}

/// One Levenberg-Marquardt iteration's damping search: from `lambda`, each damped step
/// ([`damped_step`], `(t m, δφ rad)`) is offered to `accept` and `lambda` raised tenfold until
/// one is accepted (`lambda` then lowered fivefold, to at least 1e-9, and the step returned)
/// or `lambda` reaches 1e10 (`None`: no step lowers the cost).
pub fn damped_search(
    h: &Matrix6<f64>,
    g: &Vector6<f64>,
    lambda: &mut f64,
    mut accept: impl FnMut(&Vector6<f64>) -> bool,
) -> Option<Vector6<f64>> {
    while *lambda < 1e10 {
        let Some(step) = damped_step(h, g, *lambda) else {
            *lambda *= 10.0;
            continue;
        };
        if accept(&step) {
            *lambda = (*lambda * 0.2).max(1e-9);
            return Some(step);
        }
        *lambda *= 10.0;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::{damped_search, damped_step};
    use nalgebra::{Matrix6, Vector6};

    /// The search offers steps at λ, 10λ, 100λ, … and returns the first accepted one, λ then
    /// lowered fivefold; with none accepted it gives up at 1e10.
    #[test]
    fn the_damping_search_raises_lambda_until_a_step_is_accepted() {
        let h = Matrix6::from_diagonal(&Vector6::new(1.0, 2.0, 3.0, 4.0, 5.0, 6.0));
        let g = Vector6::new(1.0, -1.0, 0.5, 0.0, 2.0, -0.5);
        // Accept the third offer (λ = 1e-2 from 1e-4).
        let mut lambda = 1e-4;
        let mut offers = Vec::new();
        let step = damped_search(&h, &g, &mut lambda, |s| {
            offers.push(*s);
            offers.len() == 3
        })
        .expect("accepted");
        assert_eq!(offers.len(), 3);
        assert_eq!(step, damped_step(&h, &g, 1e-2).expect("SPD"));
        // Each offer is shorter than the one before (more damping).
        assert!(offers[0].norm() > offers[1].norm() && offers[1].norm() > offers[2].norm());
        assert!((lambda - 2e-3).abs() < 1e-15, "{lambda}");
        // Never accepted: no step, λ at the bound.
        let mut lambda = 1e-4;
        let mut count = 0;
        assert!(
            damped_search(&h, &g, &mut lambda, |_| {
                count += 1;
                false
            })
            .is_none()
        );
        assert!(lambda >= 1e10);
        assert_eq!(count, 14);
        // A negative curvature that the damping (relative to the diagonal, floored at 1e-12)
        // cannot make positive definite: no step is ever offered.
        let indefinite = Matrix6::from_diagonal(&Vector6::new(1.0, 1.0, 1.0, 1.0, 1.0, -1.0));
        let mut lambda = 1e-4;
        let mut offered = false;
        assert!(
            damped_search(&indefinite, &g, &mut lambda, |_| {
                offered = true;
                true
            })
            .is_none()
        );
        assert!(!offered && lambda >= 1e10);
    }
}
