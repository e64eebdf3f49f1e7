//! Cramér-Rao bound on `T_e_t` for a geometry and the kinematic noise model.
//!
//! Observations: each line's two point-to-line distances `r_i` (pixels), which to first order
//! are Gaussian with covariance `Σ_i = σ_px² I + G_i diag(σ²) G_iᵀ` (`G_i` = the Jacobian
//! w.r.t. the 18 frame perturbations, [`super::ours::noise_jacobian`]), independent across
//! observations. The Fisher information of the six pose parameters `(t m, δφ rad)` is
//! `F = Σ J_iᵀ Σ_i⁻¹ J_i` with `J_i = ∂r_i/∂(t, δφ)` at the truth; the bound is `F⁻¹`. It
//! bounds unbiased estimators that use the lines only (not where the tip appears on them).

use nalgebra::{Isometry3, Matrix6};

use super::ours::{residual_and_jacobian, residual_covariance};
use super::prepare::{PrepareError, prepare};
use super::{KinematicNoise, Observation, Setup};

/// The bound and its summaries.
#[derive(Clone, Copy, Debug)]
pub struct Crb {
    /// `F⁻¹`, order `(tx, ty, tz m, φx, φy, φz rad)`.
    pub covariance: Matrix6<f64>,
    /// `√tr Σ_tt`: the bound on the RMS translation error, metres.
    pub translation_rms_m: f64,
    /// `√tr Σ_φφ`: the bound on the RMS rotation error, radians.
    pub rotation_rms_rad: f64,
}

/// Why the bound cannot be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CrbError {
    /// Input or counting check failed.
    #[error(transparent)]
    Prepare(#[from] PrepareError),
    /// The noise model has a negative, non-finite or all-zero standard deviation.
    #[error("invalid noise model: standard deviations must be finite, ≥ 0, not all zero")]
    NoiseModel,
    /// The Fisher information is singular: the pose is not observable from this geometry.
    #[error("singular Fisher information: the pose is not observable from this geometry")]
    Singular,
}

/// The Cramér-Rao bound at `truth` (`T_e_t`, metres) for these observations' joints and
/// lines under `noise`.
pub fn cramer_rao_bound(
    setup: &Setup,
    observations: &[Observation],
    truth: &Isometry3<f64>,
    noise: &KinematicNoise,
) -> Result<Crb, CrbError> {
    if !noise.is_valid() {
        return Err(CrbError::NoiseModel);
    }
    let set = prepare(setup, observations)?;
    let r = truth.rotation.to_rotation_matrix().into_inner();
    let t = truth.translation.vector;
    let mut fisher = Matrix6::zeros();
    for o in &set.obs {
        let (_, j) = residual_and_jacobian(&set, o, &r, &t);
        let s = residual_covariance(&set, o, &r, &t, noise);
        let Some(si) = s.try_inverse() else {
            return Err(CrbError::Singular);
        };
        fisher += j.transpose() * si * j;
    }
    let cov = fisher.try_inverse().ok_or(CrbError::Singular)?;
    let tt = cov[(0, 0)] + cov[(1, 1)] + cov[(2, 2)];
    let rr = cov[(3, 3)] + cov[(4, 4)] + cov[(5, 5)];
    if !(tt >= 0.0 && rr >= 0.0 && tt.is_finite() && rr.is_finite()) {
        return Err(CrbError::Singular);
    }
    Ok(Crb { covariance: cov, translation_rms_m: tt.sqrt(), rotation_rms_rad: rr.sqrt() })
}
