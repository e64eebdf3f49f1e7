//! Low-variance resampling (the paper's Algorithm 3, as in Thrun, Burgard and Fox's
//! *Probabilistic Robotics*): one uniform draw `u0 ∈ [0, 1)`, `M` equally spaced pointers.

/// Why weights cannot be resampled.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ResampleError {
    /// No weights, or an output of another length than the weights.
    #[error("resampling needs as many output slots as weights, at least one ({weights} weights, {out} slots)")]
    Length {
        /// Weights given.
        weights: usize,
        /// Output slots.
        out: usize,
    },
    /// A weight is negative or not finite, or they sum to zero.
    #[error("weights must be finite, non-negative and not all zero")]
    Weights,
    /// `u0` is not in `[0, 1)`.
    #[error("the uniform draw must be in [0, 1)")]
    Draw,
}

/// Fills `out` with the indices of the particles drawn from `weights` (not necessarily
/// normalised): particle `i` is drawn `floor` or `ceil` of `M·wᵢ/Σw` times, and the indices
/// are non-decreasing. `u0` is the one uniform draw in `[0, 1)`. Allocation-free.
pub fn low_variance(weights: &[f64], u0: f64, out: &mut [usize]) -> Result<(), ResampleError> {
    let m = weights.len();
    if m == 0 || out.len() != m {
        return Err(ResampleError::Length { weights: m, out: out.len() });
    }
    if !(0.0..1.0).contains(&u0) {
        return Err(ResampleError::Draw);
    }
    let mut total = 0.0;
    for &w in weights {
        if !(w.is_finite() && w >= 0.0) {
            return Err(ResampleError::Weights);
        }
        total += w;
    }
    if !(total > 0.0 && total.is_finite()) {
        return Err(ResampleError::Weights);
    }
    let step = total / m as f64;
    let mut c = weights[0];
    let mut i = 0usize;
    for (k, slot) in out.iter_mut().enumerate() {
        let u = (u0 + k as f64) * step;
        while u >= c && i + 1 < m {
            i += 1;
            c += weights[i];
        }
        *slot = i;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn counts_are_floor_or_ceil_of_the_expected_and_sorted(
            w in proptest::collection::vec(0.0f64..10.0, 1..200),
            u0 in 0.0f64..1.0,
        ) {
            prop_assume!(w.iter().sum::<f64>() > 1e-9);
            let mut out = vec![0usize; w.len()];
            low_variance(&w, u0, &mut out).unwrap();
            let total: f64 = w.iter().sum();
            let m = w.len() as f64;
            let mut counts = vec![0usize; w.len()];
            for win in out.windows(2) {
                prop_assert!(win[0] <= win[1]);
            }
            for &i in &out {
                prop_assert!(i < w.len());
                counts[i] += 1;
            }
            for (i, &c) in counts.iter().enumerate() {
                let e = m * w[i] / total;
                // Floor or ceil of the expected count (1e-6: rounding at whole numbers).
                prop_assert!((c as f64 - e).abs() <= 1.0 + 1e-6, "particle {} drawn {} times, expected {}", i, c, e);
                if w[i] == 0.0 {
                    prop_assert_eq!(c, 0);
                }
            }
        }
    }

    #[test]
    fn bad_weights_are_typed_errors() {
        let mut out = [0usize; 3];
        assert_eq!(low_variance(&[1.0, f64::NAN, 1.0], 0.5, &mut out), Err(ResampleError::Weights));
        assert_eq!(low_variance(&[0.0, 0.0, 0.0], 0.5, &mut out), Err(ResampleError::Weights));
        assert_eq!(low_variance(&[1.0, -1.0, 1.0], 0.5, &mut out), Err(ResampleError::Weights));
        assert_eq!(low_variance(&[1.0, 1.0, 1.0], 1.0, &mut out), Err(ResampleError::Draw));
        assert!(matches!(low_variance(&[], 0.5, &mut []), Err(ResampleError::Length { .. })));
        assert!(matches!(low_variance(&[1.0, 1.0], 0.5, &mut out), Err(ResampleError::Length { .. })));
    }
}
