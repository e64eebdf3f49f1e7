//! The Hausman-type test of the selection-aware stage's move from the guarded fit.
//!
//! Two estimators of the same pose: the guarded fit `θ_g` (covariance `Σ_g`, a robust fit of a
//! subset of the lines) and the selection-aware stage `θ_s` (covariance `Σ_s`, all lines with
//! their selection), the stage being the more efficient one when both are consistent. Under
//! that hypothesis the difference `d = θ_s − θ_g` is, to first order, normal with covariance
//! `Σ_g − Σ_s` (Hausman, "Specification tests in econometrics", Econometrica 1978: an
//! efficient estimator is uncorrelated with its difference from any other consistent one), so
//! `H = dᵀ (Σ_g − Σ_s)⁺ d` is χ² with as many degrees of freedom as the rank of the difference.
//!
//! **A difference that is not positive definite.** The two covariances are estimated (at two
//! poses, each scaled by its own dispersion, the stage leaving some lines out), so `Σ_g − Σ_s`
//! need not be positive definite. The test is computed in the stage's whitened coordinates
//! (invariant to the units of translation and rotation): with `Σ_s = L Lᵀ` and the eigen
//! decomposition `L⁻¹ Σ_g L⁻ᵀ = V Λ Vᵀ`, the difference is `L V (Λ − I) Vᵀ Lᵀ`, and the
//! move's whitened components `y = Vᵀ L⁻¹ d` are independent under the hypothesis. Each
//! direction's variance:
//! - where the stage is more efficient by at least [`MIN_VARIANCE_GAIN`] (`λ_i − 1 ≥ 0.05`):
//!   Hausman's `λ_i − 1` (the positive part of the difference);
//! - elsewhere the efficiency argument does not hold (the two fits are equally precise there,
//!   or the stage, which leaves some lines out, is less precise) and `λ_i − 1` is no variance:
//!   the largest variance the difference of two consistent estimators with variances `1` and
//!   `λ_i` can have whatever their correlation, `(1 + √λ_i)²` (Cauchy-Schwarz). Conservative:
//!   a move there is refused only when no correlation explains it, so a stage that diverges in
//!   a direction the guarded fit already determined is still refused.
//!
//! The statistic `Σ_i y_i² / v_i` then has all six directions, each of variance at most 1
//! under the hypothesis, and is compared with the χ²₆ quantile at one minus the stated
//! false-refusal probability (exact on the Hausman directions, conservative on the others).
//! The result states how many directions were Hausman's (`hausman_rank`).
//!
//! **Measured instead of assumed** ([`influence_move_test`]; the selection stage's
//! [`super::selection::SelectionConfig::influence_move_test`]). The difference's covariance
//! can also be measured: each observation's influence on the stage minus its influence on the
//! guarded fit, summed as outer products (the two fits' stacked sandwich). It needs neither
//! fit to be efficient, nor a floor, and uses the residuals' real dispersion for both fits.

use nalgebra::{Matrix6, Vector6};

/// Smallest `λ_i − 1` (variance of the difference over the stage's variance, in the stage's
/// whitened eigen-directions) for a direction to be tested (dimensionless).
pub const MIN_VARIANCE_GAIN: f64 = 0.05;

/// Fewest observations with a non-zero influence for [`influence_move_test`] (five per
/// covariance entry of the 6 × 6 difference's 21).
pub const MIN_INFLUENCES: usize = 105;

/// The test's outcome.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MoveTest {
    /// `dᵀ (Σ_g − Σ_s)⁺ d` on the tested directions (dimensionless; χ² with `dof` degrees of
    /// freedom when both estimators are consistent).
    pub statistic: f64,
    /// Degrees of freedom (6 for [`move_test`]: every direction is tested; for
    /// [`influence_move_test`], the directions with a measured variance).
    pub dof: usize,
    /// [`move_test`]: directions judged by Hausman's variance `λ_i − 1` (0-6), the others by
    /// the Cauchy-Schwarz bound (module docs); [`influence_move_test`]: equal to `dof`.
    pub hausman_rank: usize,
    /// Which test: `true` for the move's covariance measured from the observations'
    /// influences ([`influence_move_test`]), `false` for the efficiency-based variances
    /// ([`move_test`]).
    pub measured: bool,
    /// The refusal limit: the χ² quantile of `dof` degrees of freedom at one minus the
    /// false-refusal probability.
    pub limit: f64,
}

impl MoveTest {
    /// True when the move is within the limit.
    pub fn passes(&self) -> bool {
        self.statistic <= self.limit
    }
}

/// The test of the move `d` (`(t m, δφ rad)`, stage minus guarded fit) with the guarded fit's
/// covariance `start_cov` and the stage's `stage_cov` (both of `(t m, δφ rad)`), refusing with
/// probability `false_refusal` (in `(0, 1)`) when both estimators are consistent. `None` when
/// an input is not finite or the stage's covariance is not positive definite.
pub fn move_test(
    d: &Vector6<f64>,
    start_cov: &Matrix6<f64>,
    stage_cov: &Matrix6<f64>,
    false_refusal: f64,
) -> Option<MoveTest> {
    if !(d.iter().chain(start_cov.iter()).chain(stage_cov.iter()).all(|v| v.is_finite())
        && false_refusal > 0.0
        && false_refusal < 1.0)
    {
        return None;
    }
    let sym = |m: &Matrix6<f64>| (m + m.transpose()) * 0.5;
    let l = sym(stage_cov).cholesky()?.l();
    let l_inv = l.try_inverse()?;
    let m = sym(&(l_inv * start_cov * l_inv.transpose()));
    let eig = m.symmetric_eigen();
    let z = l_inv * d;
    let (mut statistic, mut hausman_rank) = (0.0, 0usize);
    for i in 0..6 {
        let lambda = eig.eigenvalues[i].max(0.0);
        let var = if lambda - 1.0 >= MIN_VARIANCE_GAIN {
            hausman_rank += 1;
            lambda - 1.0
        } else {
            (1.0 + lambda.sqrt()).powi(2)
        };
        let y = eig.eigenvectors.column(i).dot(&z);
        statistic += y * y / var;
    }
    Some(MoveTest { statistic, dof: 6, hausman_rank, limit: chi2_quantile(6, 1.0 - false_refusal), measured: false })
}

/// The move test with the difference's covariance measured from the data: `influence[i]` is
/// observation `i`'s influence on the difference of the two fits (`(t m, δφ rad)`: the
/// stage's minus the guarded fit's, each its inverse Gauss-Newton matrix times the
/// observation's score; zero where an observation is in neither fit). Their centred sum of
/// outer products estimates the covariance of `d` whatever the two fits' efficiency (the
/// sandwich covariance of two M-estimators stacked: White, "Maximum likelihood estimation of
/// misspecified models", Econometrica 1982; Weesie, "Seemingly unrelated estimation and the
/// cluster-adjusted sandwich estimator", Stata Technical Bulletin 1999), so no direction needs
/// the efficiency argument or [`MIN_VARIANCE_GAIN`]'s floor: the statistic `dᵀ V⁺ d` is
/// continuous in the data. Directions whose variance is below `1e-12` of the largest are left
/// out (`dof` counts the others; `hausman_rank` = `dof`). `None` when an input is not finite,
/// fewer than [`MIN_INFLUENCES`] observations have an influence (a 6 × 6 covariance from a
/// handful of vectors is no χ² yardstick), or a component's variance is zero.
pub fn influence_move_test(d: &Vector6<f64>, influence: &[Vector6<f64>], false_refusal: f64) -> Option<MoveTest> {
    if !(d.iter().all(|v| v.is_finite())
        && influence.iter().all(|u| u.iter().all(|v| v.is_finite()))
        && false_refusal > 0.0
        && false_refusal < 1.0)
    {
        return None;
    }
    let active = influence.iter().filter(|u| u.iter().any(|v| *v != 0.0)).count();
    if active < MIN_INFLUENCES {
        return None;
    }
    let mean = influence.iter().fold(Vector6::zeros(), |a, u| a + u) / influence.len() as f64;
    let v = influence.iter().fold(Matrix6::zeros(), |a, u| {
        let c = u - mean;
        a + c * c.transpose()
    });
    // In the units-free coordinates of V's own scale per component, then its eigen-directions.
    let s = Vector6::from_fn(|i, _| v[(i, i)].max(0.0).sqrt());
    if s.iter().any(|x| !(x.is_finite() && *x > 0.0)) {
        return None;
    }
    let corr = Matrix6::from_fn(|i, j| v[(i, j)] / (s[i] * s[j]));
    let z = d.component_div(&s);
    let eig = ((corr + corr.transpose()) * 0.5).symmetric_eigen();
    let top = eig.eigenvalues.max();
    let (mut statistic, mut dof) = (0.0, 0usize);
    for i in 0..6 {
        let lambda = eig.eigenvalues[i];
        if lambda > 1e-12 * top {
            let y = eig.eigenvectors.column(i).dot(&z);
            statistic += y * y / lambda;
            dof += 1;
        }
    }
    (dof > 0).then(|| MoveTest {
        statistic,
        dof,
        hausman_rank: dof,
        limit: chi2_quantile(dof, 1.0 - false_refusal),
        measured: true,
    })
}

/// Survival function `P(X > x)` of the χ² distribution with `k ≥ 1` degrees of freedom (closed
/// form for integer `k`; 1 for `x ≤ 0`).
pub fn chi2_survival(k: usize, x: f64) -> f64 {
    if x.is_nan() {
        return f64::NAN;
    }
    if x <= 0.0 {
        return 1.0;
    }
    let h = 0.5 * x;
    if k.is_multiple_of(2) {
        // e^{−x/2} Σ_{j<k/2} (x/2)^j / j!
        let (mut term, mut sum) = (1.0, 1.0);
        for j in 1..k / 2 {
            term *= h / j as f64;
            sum += term;
        }
        (-h).exp() * sum
    } else {
        // erfc(√(x/2)) + √(2x/π) e^{−x/2} Σ_{j=1}^{(k−1)/2} x^{j−1} / (1·3···(2j−1))
        let mut sum = 0.0;
        let mut term = 1.0;
        for j in 1..=(k - 1) / 2 {
            if j > 1 {
                term *= x / (2 * j - 1) as f64;
            }
            sum += term;
        }
        libm::erfc(h.sqrt()) + (2.0 * x / core::f64::consts::PI).sqrt() * (-h).exp() * sum
    }
}

/// The `p`-quantile of the χ² distribution with `k ≥ 1` degrees of freedom (`p` in `(0, 1)`),
/// by bisection of [`chi2_survival`] to a relative 1e-12.
pub fn chi2_quantile(k: usize, p: f64) -> f64 {
    let target = 1.0 - p;
    let (mut lo, mut hi) = (0.0f64, (k as f64).max(1.0));
    while chi2_survival(k, hi) > target && hi < 1e6 {
        hi *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if chi2_survival(k, mid) > target {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-12 * hi {
            break;
        }
    }
    0.5 * (lo + hi)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix6;

    #[test]
    fn chi2_quantiles_match_tables() {
        // Standard table values (Abramowitz & Stegun 26.8).
        for (k, p, q) in [
            (1, 0.95, 3.841_458_8),
            (2, 0.95, 5.991_464_5),
            (3, 0.999, 16.266_236),
            (6, 0.95, 12.591_587),
            (6, 0.999, 22.457_744),
            (5, 0.99, 15.086_272),
        ] {
            let got = chi2_quantile(k, p);
            assert!((got - q).abs() < 1e-5 * q, "k {k} p {p}: {got} vs {q}");
        }
    }

    fn covs() -> (Matrix6<f64>, Matrix6<f64>) {
        // A guarded fit three times wider in variance than the stage, with mixed units
        // (metres and radians) and correlations.
        let a = Matrix6::from_fn(|i, j| if i == j { 1.0 } else { 0.1 * ((i + 2 * j) % 3) as f64 - 0.1 });
        let s = Matrix6::from_diagonal(&Vector6::new(1e-3, 2e-3, 1.5e-3, 1e-2, 2e-2, 5e-3));
        let stage = s * a * a.transpose() * s;
        (stage * 3.0, stage)
    }

    #[test]
    fn a_move_within_the_noise_passes_and_a_run_away_is_refused() {
        let (g, s) = covs();
        // A move of one standard deviation of the difference along each whitened direction
        // in turn (statistic 1 per direction): passes.
        let diff = g - s;
        let c = diff.cholesky().unwrap().l();
        for i in 0..6 {
            let d = c.column(i).into_owned();
            let t = move_test(&d, &g, &s, 1e-3).unwrap();
            assert_eq!((t.dof, t.hausman_rank), (6, 6));
            assert!((t.statistic - 1.0).abs() < 1e-9, "{}", t.statistic);
            assert!(t.passes());
        }
        // Five standard deviations of the difference in every direction: χ² = 150 ≫ 22.5.
        let d = c * Vector6::repeat(5.0);
        let t = move_test(&d, &g, &s, 1e-3).unwrap();
        assert!((t.statistic - 150.0).abs() < 1e-6 && !t.passes(), "{t:?}");
        // The statistic does not depend on the units (metres vs millimetres).
        let k = Matrix6::from_diagonal(&Vector6::new(1e3, 1e3, 1e3, 1.0, 1.0, 1.0));
        let t_mm = move_test(&(k * d), &(k * g * k), &(k * s * k), 1e-3).unwrap();
        assert!((t_mm.statistic - t.statistic).abs() < 1e-6 * t.statistic);
    }

    #[test]
    fn a_difference_that_is_not_positive_definite_is_tested_on_its_positive_part() {
        let (_, s) = covs();
        // The guarded fit wider than the stage in two whitened directions only, narrower in
        // two, equal in two.
        let l = s.cholesky().unwrap().l();
        let lam = Vector6::new(4.0, 2.0, 1.0, 1.0, 0.5, 0.25);
        let g = l * Matrix6::from_diagonal(&lam) * l.transpose();
        // A move along the first whitened direction: 2 sd of the difference (Hausman: √3 · 2)
        // and 1 sd along the sixth by the Cauchy-Schwarz bound ((1 + √0.25)² = 2.25).
        let mut z = Vector6::zeros();
        z[0] = 2.0 * 3f64.sqrt();
        z[5] = 1.5;
        let t = move_test(&(l * z), &g, &s, 1e-3).unwrap();
        assert_eq!((t.dof, t.hausman_rank), (6, 2));
        assert!((t.statistic - 5.0).abs() < 1e-9, "{t:?}");
        assert!((t.limit - chi2_quantile(6, 0.999)).abs() < 1e-12 && t.passes());
        // The stage nowhere more efficient, and a move of 50 sd of the guarded fit along a
        // direction it determined (a diverged stage): refused though no Hausman direction.
        let mut z = Vector6::zeros();
        z[2] = 50.0;
        let t0 = move_test(&(l * z), &s, &s, 1e-3).unwrap();
        assert_eq!(t0.hausman_rank, 0);
        assert!((t0.statistic - 2500.0 / 4.0).abs() < 1e-6 && !t0.passes(), "{t0:?}");
    }

    /// Influences of a difference with covariance `c` (a 6×6 SPD), drawn deterministically:
    /// `n` vectors whose centred outer products sum to `c` exactly (± columns of its factor,
    /// scaled).
    fn influences_with_covariance(c: &Matrix6<f64>, n: usize) -> Vec<Vector6<f64>> {
        let l = c.cholesky().unwrap().l();
        let k = n / 12;
        let scale = (1.0 / (2.0 * k as f64)).sqrt();
        let mut out = Vec::new();
        for i in 0..6 {
            for sign in [1.0, -1.0] {
                for _ in 0..k {
                    out.push(l.column(i) * (sign * scale));
                }
            }
        }
        out
    }

    #[test]
    fn the_measured_difference_covariance_scores_a_move_by_its_own_spread() {
        let (g, s) = covs();
        let diff = g - s;
        let u = influences_with_covariance(&diff, 120);
        // The influences' covariance is `diff`: a move of one of its standard deviations along
        // each factor column scores 1, five in every direction 150, in any units.
        let c = diff.cholesky().unwrap().l();
        for i in 0..6 {
            let t = influence_move_test(&c.column(i).into_owned(), &u, 1e-3).unwrap();
            assert_eq!((t.dof, t.hausman_rank), (6, 6));
            assert!((t.statistic - 1.0).abs() < 1e-6, "{t:?}");
            assert!(t.passes());
        }
        let d = c * Vector6::repeat(5.0);
        let t = influence_move_test(&d, &u, 1e-3).unwrap();
        assert!((t.statistic - 150.0).abs() < 1e-4 && !t.passes(), "{t:?}");
        let k = Matrix6::from_diagonal(&Vector6::new(1e3, 1e3, 1e3, 1.0, 1.0, 1.0));
        let u_mm: Vec<_> = u.iter().map(|x| k * x).collect();
        let t_mm = influence_move_test(&(k * d), &u_mm, 1e-3).unwrap();
        assert!((t_mm.statistic - t.statistic).abs() < 1e-6 * t.statistic);
        // No floor: where the efficiency-based test switches from λ − 1 to the Cauchy-Schwarz
        // bound (a 4 % vs a 6 % gain), the measured test changes by the ratio of the spreads.
        let l = s.cholesky().unwrap().l();
        let mut z = Vector6::zeros();
        z[0] = 0.5;
        for (gain, expect_eff) in [(0.06, 0.25 / 0.06), (0.04, 0.25 / (1.0 + 1.04f64.sqrt()).powi(2))] {
            let gm = l * Matrix6::from_diagonal(&Vector6::new(1.0 + gain, 2.0, 2.0, 2.0, 2.0, 2.0)) * l.transpose();
            let eff = move_test(&(l * z), &gm, &s, 1e-3).unwrap();
            assert!((eff.statistic - expect_eff).abs() < 1e-9, "{eff:?}");
            let dm = l * Matrix6::from_diagonal(&Vector6::new(gain, 1.0, 1.0, 1.0, 1.0, 1.0)) * l.transpose();
            let meas = influence_move_test(&(l * z), &influences_with_covariance(&dm, 120), 1e-3).unwrap();
            assert!((meas.statistic - 0.25 / gain).abs() < 1e-6 * meas.statistic, "{gain}: {meas:?}");
        }
        // Too few observations, or one that is not finite: no test.
        assert!(influence_move_test(&d, &u[..MIN_INFLUENCES - 1], 1e-3).is_none());
        let mut bad = u.clone();
        bad[3][2] = f64::NAN;
        assert!(influence_move_test(&d, &bad, 1e-3).is_none());
    }

    #[test]
    fn bad_inputs_give_none() {
        let (g, s) = covs();
        let d = Vector6::repeat(1e-3);
        assert!(move_test(&d, &g, &-s, 1e-3).is_none());
        assert!(move_test(&Vector6::repeat(f64::NAN), &g, &s, 1e-3).is_none());
        assert!(move_test(&d, &g, &s, 0.0).is_none());
        assert!(move_test(&d, &g, &s, 1.0).is_none());
    }
}
