//! Least-squares intersection of 3-D lines (the paper's Eq. 3-8), as O(1) sliding sums.
//!
//! For a line through `p` with unit direction `z`, `M = I − z zᵀ` projects onto the plane
//! normal to the line, and the distance from a point F to the line is `|M (F − p)|`. The
//! point minimising `Σ |M_i (F − p_i)|²` solves the normal equations
//! `(Σ M_i) F = Σ M_i p_i` (Eq. 7; `M` is symmetric and idempotent, so `AᵀA = Σ M_i`).
//! [`NormalSums`] keeps `A = Σ M_i`, `b = Σ M_i p_i` and `c = Σ p_iᵀ M_i p_i`, so lines can be
//! added and removed in O(1), and the sum of squared residuals at the optimum is
//! `c − bᵀF` without revisiting the lines.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use super::LineSample;

/// Running sums of the normal equations over a set of lines (metres, robot base frame).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NormalSums {
    /// `Σ (I − z zᵀ)` (dimensionless).
    a: Matrix3<f64>,
    /// `Σ (I − z zᵀ) p`, metres.
    b: Vector3<f64>,
    /// `Σ pᵀ (I − z zᵀ) p`, square metres.
    c: f64,
    /// Number of lines in the sums.
    count: u32,
    /// Total weight of the lines (equal to `count` unless [`NormalSums::decay`] was used).
    weight: f64,
}

impl Default for NormalSums {
    fn default() -> Self {
        Self { a: Matrix3::zeros(), b: Vector3::zeros(), c: 0.0, count: 0, weight: 0.0 }
    }
}

/// Why a least-squares fulcrum could not be computed.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum SolveError {
    /// Fewer than two lines.
    #[error("fewer than two lines ({count})")]
    TooFewLines {
        /// Lines available.
        count: u32,
    },
    /// The lines are (nearly) parallel: the smallest eigenvalue of `Σ(I − z zᵀ)` divided by
    /// the number of lines is below the gate, so the intersection is undetermined.
    #[error("lines nearly parallel: conditioning {conditioning:.3e} below {gate:.3e}")]
    IllConditioned {
        /// `λ_min(Σ(I − z zᵀ)) / q`.
        conditioning: f64,
        /// The gate it failed.
        gate: f64,
    },
    /// Non-finite arithmetic (cannot happen with finite unit inputs; kept as a last guard).
    #[error("non-finite least-squares solution")]
    NonFinite,
}

/// A least-squares fulcrum and its quality figures.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LsFit {
    /// Point closest to all lines, metres, robot base frame.
    pub fulcrum_base_m: Vector3<f64>,
    /// Sum of squared distances from the point to the lines, square metres.
    pub ssr_m2: f64,
    /// Root-mean-square distance from the point to the lines, metres.
    pub rms_m: f64,
    /// `λ_min(Σ(I − z zᵀ)) / q`: 0 for parallel lines, at most 2/3; roughly the mean squared
    /// angular spread (rad²) of the lines about their mean direction.
    pub conditioning: f64,
    /// Standard deviation (metres) of the fulcrum along its worst direction, for a per-line
    /// noise `sigma_m`: `sigma_m / sqrt(λ_min)`. Multiply by the noise you assume.
    pub std_per_unit_noise: f64,
    /// Number of lines.
    pub count: u32,
    /// Total weight of the lines (`count` without forgetting).
    pub weight: f64,
    /// `1 − λ_max(Σ(I − z zᵀ)) / q`: about the mean squared angular spread (rad²) of the
    /// lines' directions along their *narrowest* direction of spread (0 when every line lies
    /// in one plane through the mean direction, as in a one-axis swing).
    pub minor_spread_rad2: f64,
}

impl LsFit {
    /// Standard deviation (metres) of the fulcrum along its worst direction for a per-line
    /// noise of `sigma_m` metres.
    pub fn fulcrum_std_m(&self, sigma_m: f64) -> f64 {
        sigma_m * self.std_per_unit_noise
    }

    /// Unbiased estimate (metres) of the per-line noise: `sqrt(SSR / (2q − 3))` (each line
    /// gives two constraints, the fulcrum takes three).
    pub fn noise_estimate_m(&self) -> f64 {
        let dof = (2.0 * self.weight - 3.0).max(1.0);
        libm_sqrt(self.ssr_m2 / dof)
    }
}

#[inline]
fn libm_sqrt(x: f64) -> f64 {
    nalgebra::ComplexField::sqrt(x)
}

/// Squared distance (m²) from `point` to the line `(p, z)`; `z` must be unit.
#[inline]
pub fn line_distance_sq(line: &LineSample, point: &Vector3<f64>) -> f64 {
    let v = point - line.wrist_base_m;
    let along = line.axis_base.dot(&v);
    (v.norm_squared() - along * along).max(0.0)
}

/// Distance (m) from `point` to the line `(p, z)`.
#[inline]
pub fn line_distance(line: &LineSample, point: &Vector3<f64>) -> f64 {
    libm_sqrt(line_distance_sq(line, point))
}

/// Signed depth (m) of `point` along the line from the wrist: `zᵀ(F − P)`. Positive when the
/// point lies in front of the wrist, towards the instrument tip.
#[inline]
pub fn signed_depth(line: &LineSample, point: &Vector3<f64>) -> f64 {
    line.axis_base.dot(&(point - line.wrist_base_m))
}

impl NormalSums {
    /// Empty sums.
    pub fn new() -> Self {
        Self::default()
    }

    /// Number of lines in the sums.
    pub fn count(&self) -> u32 {
        self.count
    }

    #[inline]
    fn terms(line: &LineSample) -> (Matrix3<f64>, Vector3<f64>, f64) {
        let z = &line.axis_base;
        let m = Matrix3::identity() - z * z.transpose();
        let mp = m * line.wrist_base_m;
        (m, mp, line.wrist_base_m.dot(&mp))
    }

    /// Adds a line.
    #[inline]
    pub fn add(&mut self, line: &LineSample) {
        let (m, mp, c) = Self::terms(line);
        self.a += m;
        self.b += mp;
        self.c += c;
        self.count += 1;
        self.weight += 1.0;
    }

    /// Forgets part of every line in the sums: each line's weight is multiplied by `keep`
    /// (in (0, 1]). With one `decay` before each `add`, the sums weigh the k-th most recent
    /// line by `keep^k` (exponential forgetting, memory about `1 / (1 − keep)` lines).
    #[inline]
    pub fn decay(&mut self, keep: f64) {
        self.a *= keep;
        self.b *= keep;
        self.c *= keep;
        self.weight *= keep;
    }

    /// Removes a line previously added (sliding window).
    #[inline]
    pub fn remove(&mut self, line: &LineSample) {
        let (m, mp, c) = Self::terms(line);
        self.a -= m;
        self.b -= mp;
        self.c -= c;
        self.count = self.count.saturating_sub(1);
        self.weight -= 1.0;
        if self.count == 0 {
            *self = Self::default();
        }
    }

    /// Rebuilds the sums from scratch (guard against floating-point drift of long runs of
    /// add/remove).
    pub fn rebuild<'a>(&mut self, lines: impl Iterator<Item = &'a LineSample>) {
        *self = Self::default();
        for l in lines {
            self.add(l);
        }
    }

    /// Solves Eq. 7. `min_conditioning` gates `λ_min(A)/q`: below it the lines are taken as
    /// parallel and no point is returned.
    pub fn solve(&self, min_conditioning: f64) -> Result<LsFit, SolveError> {
        if self.count < 2 {
            return Err(SolveError::TooFewLines { count: self.count });
        }
        let q = self.weight;
        // NaN-safe: a NaN weight is refused like a too small one.
        if q.is_nan() || q <= 1.0 {
            return Err(SolveError::TooFewLines { count: self.count });
        }
        let eig = SymmetricEigen::new(self.a);
        let mut i_min = 0;
        for i in 1..3 {
            if eig.eigenvalues[i] < eig.eigenvalues[i_min] {
                i_min = i;
            }
        }
        let lambda_min = eig.eigenvalues[i_min];
        let lambda_max = eig.eigenvalues.iter().copied().fold(f64::MIN, f64::max);
        let conditioning = lambda_min / q;
        if !conditioning.is_finite() || conditioning < min_conditioning || lambda_min <= 0.0 {
            return Err(SolveError::IllConditioned {
                conditioning: if conditioning.is_finite() { conditioning } else { 0.0 },
                gate: min_conditioning,
            });
        }
        // F = V Λ⁻¹ Vᵀ b
        let vt_b = eig.eigenvectors.transpose() * self.b;
        let scaled =
            Vector3::new(vt_b[0] / eig.eigenvalues[0], vt_b[1] / eig.eigenvalues[1], vt_b[2] / eig.eigenvalues[2]);
        let f = eig.eigenvectors * scaled;
        let ssr = (self.c - self.b.dot(&f)).max(0.0);
        if !(f.iter().all(|x| x.is_finite()) && ssr.is_finite()) {
            return Err(SolveError::NonFinite);
        }
        Ok(LsFit {
            fulcrum_base_m: f,
            ssr_m2: ssr,
            rms_m: libm_sqrt(ssr / q),
            conditioning,
            std_per_unit_noise: 1.0 / libm_sqrt(lambda_min),
            count: self.count,
            weight: q,
            minor_spread_rad2: (1.0 - lambda_max / q).max(0.0),
        })
    }
}

/// Mean distance from `point` to the lines (the paper's Eq. 8 error `e_q`), metres.
pub fn mean_distance<'a>(lines: impl Iterator<Item = &'a LineSample>, point: &Vector3<f64>) -> f64 {
    let mut sum = 0.0;
    let mut n = 0u32;
    for l in lines {
        sum += line_distance(l, point);
        n += 1;
    }
    if n == 0 { 0.0 } else { sum / n as f64 }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;
    use proptest::prelude::*;
    use std::vec::Vec;

    use super::{NormalSums, SolveError};
    use crate::trocar::LineSample;
    use crate::trocar::test_support::{cone_axis, line_through};

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
}
