//! The paper's pipeline, faithful: translation by linear least squares (Eq. 5), rotation by
//! the Kronecker linear method with projection onto SO(3) (Eq. 7-9), then the quaternion
//! nonlinear refinement (Eq. 10) started from the linear result.
//!
//! Choices the paper leaves open, and ours: plane normals are unit vectors (Eq. 1 normalised);
//! Eq. 5 is solved through its 3×3 normal equations; Eq. 8 is the eigenvector of the smallest
//! eigenvalue of `Σ kᵢkᵢᵀ`; Remark 1's projection is the SVD one; Eq. 10 is minimised by
//! Levenberg-Marquardt on the four quaternion components with the scale-free residual
//! `qᵀWq / qᵀq` (the `‖q‖²` of Eq. 10's third line), renormalised after each step.

use nalgebra::{
    Isometry3, Matrix3, Matrix4, Quaternion, Rotation3, SMatrix, SVector, SymmetricEigen, Translation3, UnitQuaternion,
    Vector3, Vector4,
};

use super::prepare::{PrepareError, PreparedSet, prepare};
use super::{Observation, Setup};

/// Eq. 5 and Eq. 8 refuse systems whose smallest (Eq. 5) or second-smallest (Eq. 8)
/// eigenvalue is below this fraction of the largest one.
pub const RANK_TOLERANCE: f64 = 1e-10;

/// Why the paper's pipeline failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PaperError {
    /// Input or counting check failed (see [`PrepareError`]).
    #[error(transparent)]
    Prepare(#[from] PrepareError),
    /// Degenerate: every view of robot 1 lies on one line through robot 2's RCM (the
    /// endoscope only moved toward or away from robot 2's RCM), so Eq. 5 has no unique
    /// solution.
    #[error(
        "degenerate data: robot 1's views are collinear with the line from robot 2's RCM to the camera (Eq. 5 rank-deficient, eigenvalue ratio {ratio:.1e}); move the endoscope sideways"
    )]
    ViewsCollinear {
        /// Smallest over largest eigenvalue of Eq. 5's normal matrix.
        ratio: f64,
    },
    /// Degenerate: every observed line passes through one image point (or all are parallel or
    /// identical), which a tool pivoting about a fixed RCM seen from two or more views not
    /// collinear with it cannot produce: Eq. 1's normals span fewer than three dimensions and
    /// the lines carry no information on the pose.
    #[error(
        "degenerate data: the observed lines form a single pencil (identical, parallel or concurrent; eigenvalue ratio of the plane normals {ratio:.1e} < {tol:.0e}); check the line detector",
        tol = super::prepare::PENCIL_TOLERANCE
    )]
    LinesFormOnePencil {
        /// Smallest over largest eigenvalue of `Σ n_c n_cᵀ` (camera frame).
        ratio: f64,
    },
    /// Degenerate: Eq. 8's null space is more than one-dimensional (for the linear step the
    /// tool needs four orientations in general position, three are enough only for Eq. 10).
    #[error(
        "degenerate data: the Kronecker system (Eq. 8) has a null space of dimension > 1 (eigenvalue ratio {ratio:.1e}); record more, non-coplanar tool orientations"
    )]
    RotationUnobservable {
        /// Second-smallest over largest eigenvalue of Eq. 8's normal matrix.
        ratio: f64,
    },
}

/// Options of the paper's pipeline.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PaperConfig {
    /// Start Eq. 10 from this quaternion `[w, x, y, z]` (need not be unit, Remark 5) instead
    /// of the linear result (used by the initial-guess robustness sweep).
    pub initial_quaternion: Option<[f64; 4]>,
}

/// Result of the paper's pipeline.
#[derive(Clone, Copy, Debug)]
pub struct PaperResult {
    /// `T_e_t` (metres): translation from Eq. 5, rotation from Eq. 10.
    pub pose: Isometry3<f64>,
    /// The linear rotation (Eq. 8-9), before Eq. 10.
    pub linear_rotation: UnitQuaternion<f64>,
    /// Eq. 10's cost `Σ (nᵀ R m)²` at the solution (dimensionless).
    pub rotation_cost: f64,
    /// Levenberg-Marquardt iterations of Eq. 10.
    pub iterations: usize,
}

/// Eq. 5: `eO_t = argmin Σ (nₑᵀ x − nₑᵀ eO_c)²` (metres, `{e}`), with `nₑ = e_cR n_c`.
/// Refused when its normal matrix is rank-deficient ([`PaperError::ViewsCollinear`]) or when
/// the lines it rests on form one pencil ([`PaperError::LinesFormOnePencil`]).
pub fn linear_translation(set: &PreparedSet) -> Result<Vector3<f64>, PaperError> {
    let mut ata = Matrix3::zeros();
    let mut atb = Vector3::zeros();
    for o in &set.obs {
        ata += o.n_e * o.n_e.transpose();
        atb += o.n_e * o.n_e.dot(&o.o_ec);
    }
    let eig = SymmetricEigen::new(ata);
    let max = eig.eigenvalues.max();
    let min = eig.eigenvalues.min();
    let ratio = if max > 0.0 { min / max } else { 0.0 };
    if ratio.is_nan() || ratio <= RANK_TOLERANCE {
        return Err(PaperError::ViewsCollinear { ratio });
    }
    if set.pencil_ratio.is_nan() || set.pencil_ratio < super::prepare::PENCIL_TOLERANCE {
        return Err(PaperError::LinesFormOnePencil { ratio: set.pencil_ratio });
    }
    // Solve through the eigen-decomposition (already computed, well conditioned here).
    let mut x = Vector3::zeros();
    for i in 0..3 {
        let v = eig.eigenvectors.column(i);
        x += v * (v.dot(&atb) / eig.eigenvalues[i]);
    }
    Ok(x)
}

/// Eq. 5 for tool lines through known points `p_i` of `{t}` (an arm without a mechanical
/// RCM, [`super::Observation::tool_point_m`]), given the rotation `R = e_tR`:
/// `t = argmin Σ (nₑᵀ t − nₑᵀ (eO_c − R p_i))²` (metres, `{e}`). With every `p_i` at the
/// origin it is Eq. 5 itself (any `R`). Same refusals as [`linear_translation`].
pub fn translation_given_rotation(set: &PreparedSet, r: &Matrix3<f64>) -> Result<Vector3<f64>, PaperError> {
    let mut ata = Matrix3::zeros();
    let mut atb = Vector3::zeros();
    for o in &set.obs {
        ata += o.n_e * o.n_e.transpose();
        atb += o.n_e * o.n_e.dot(&(o.o_ec - r * o.p_t));
    }
    let eig = SymmetricEigen::new(ata);
    let max = eig.eigenvalues.max();
    let min = eig.eigenvalues.min();
    let ratio = if max > 0.0 { min / max } else { 0.0 };
    if ratio.is_nan() || ratio <= RANK_TOLERANCE {
        return Err(PaperError::ViewsCollinear { ratio });
    }
    if set.pencil_ratio.is_nan() || set.pencil_ratio < super::prepare::PENCIL_TOLERANCE {
        return Err(PaperError::LinesFormOnePencil { ratio: set.pencil_ratio });
    }
    let mut x = Vector3::zeros();
    for i in 0..3 {
        let v = eig.eigenvectors.column(i);
        x += v * (v.dot(&atb) / eig.eigenvalues[i]);
    }
    Ok(x)
}

/// One row of Eq. 7: `kᵀ = mᵀ ⊗ nₑᵀ`, so that `kᵀ Vec(R) = nₑᵀ R m` (column-major `Vec`).
pub fn kronecker_row(n_e: &Vector3<f64>, m_t: &Vector3<f64>) -> SVector<f64, 9> {
    let mut k = SVector::<f64, 9>::zeros();
    for j in 0..3 {
        for i in 0..3 {
            k[3 * j + i] = m_t[j] * n_e[i];
        }
    }
    k
}

/// Eq. 8-9: the linear rotation. `Vec(V)` is the eigenvector of the smallest eigenvalue of
/// `Σ kkᵀ`; `V` is sign-fixed by `sign(det V)` (Eq. 9) and projected onto SO(3) by SVD
/// (Remark 1; the projection makes Eq. 9's `|det V|^{1/3}` scaling redundant).
pub fn kronecker_rotation(set: &PreparedSet) -> Result<Rotation3<f64>, PaperError> {
    let mut m9 = SMatrix::<f64, 9, 9>::zeros();
    for o in &set.obs {
        let k = kronecker_row(&o.n_e, &o.m_t);
        m9 += k * k.transpose();
    }
    let eig = SymmetricEigen::new(m9);
    let mut idx: [usize; 9] = [0, 1, 2, 3, 4, 5, 6, 7, 8];
    idx.sort_by(|a, b| eig.eigenvalues[*a].total_cmp(&eig.eigenvalues[*b]));
    let max = eig.eigenvalues[idx[8]];
    let ratio = if max > 0.0 { eig.eigenvalues[idx[1]] / max } else { 0.0 };
    if ratio.is_nan() || ratio <= RANK_TOLERANCE {
        return Err(PaperError::RotationUnobservable { ratio });
    }
    let v = Matrix3::from_column_slice(eig.eigenvectors.column(idx[0]).as_slice());
    Ok(project_to_so3(&v))
}

/// Eq. 9 with Remark 1: the rotation nearest (Frobenius) to `sign(det V)·V`.
pub fn project_to_so3(v: &Matrix3<f64>) -> Rotation3<f64> {
    let v = if v.determinant() < 0.0 { -v } else { *v };
    let svd = v.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return Rotation3::identity();
    };
    let mut r = u * vt;
    if r.determinant() < 0.0 {
        let mut u2 = u;
        let c = -u2.column(2);
        u2.set_column(2, &c);
        r = u2 * vt;
    }
    Rotation3::from_matrix_unchecked(r)
}

/// Appendix B's `N` (left multiplication by the pure quaternion `(0, n)`), `[w, x, y, z]`.
pub fn quat_left(n: &Vector3<f64>) -> Matrix4<f64> {
    Matrix4::new(0.0, -n.x, -n.y, -n.z, n.x, 0.0, -n.z, n.y, n.y, n.z, 0.0, -n.x, n.z, -n.y, n.x, 0.0)
}

/// Appendix B's `M` (right multiplication by the pure quaternion `(0, m)`), `[w, x, y, z]`.
pub fn quat_right(m: &Vector3<f64>) -> Matrix4<f64> {
    Matrix4::new(0.0, -m.x, -m.y, -m.z, m.x, 0.0, m.z, -m.y, m.y, -m.z, 0.0, m.x, m.z, m.y, -m.x, 0.0)
}

/// Eq. 10's `W = Nᵀ M`: for a unit `q`, `qᵀ W q = nᵀ R(q) m`.
pub fn eq10_w(n_e: &Vector3<f64>, m_t: &Vector3<f64>) -> Matrix4<f64> {
    quat_left(n_e).transpose() * quat_right(m_t)
}

/// Eq. 10: `argmin_q Σ (qᵀ W q / qᵀq)²` from `q0 = [w, x, y, z]` (any non-zero 4-vector).
/// Returns the unit quaternion, the final cost and the iterations used.
pub fn refine_quaternion(set: &PreparedSet, q0: &Vector4<f64>) -> (UnitQuaternion<f64>, f64, usize) {
    refine_quaternion_sym(&eq10_symmetric(set), q0)
}

/// Each observation's symmetric part `(W + Wᵀ)/2` of Eq. 10's `W` ([`eq10_w`]): what
/// [`refine_quaternion_sym`] needs, computed once for several starts.
pub fn eq10_symmetric(set: &PreparedSet) -> std::vec::Vec<Matrix4<f64>> {
    set.obs
        .iter()
        .map(|o| {
            let w = eq10_w(&o.n_e, &o.m_t);
            (w + w.transpose()) * 0.5
        })
        .collect()
}

/// [`refine_quaternion`] on precomputed [`eq10_symmetric`] matrices (same arithmetic).
pub fn refine_quaternion_sym(sym: &[Matrix4<f64>], q0: &Vector4<f64>) -> (UnitQuaternion<f64>, f64, usize) {
    let cost_of = |q: &Vector4<f64>| -> f64 {
        let qq = q.dot(q);
        sym.iter().map(|s| (q.dot(&(s * q)) / qq).powi(2)).sum()
    };
    let mut q = if q0.norm() > 0.0 && q0.iter().all(|v| v.is_finite()) {
        q0.normalize()
    } else {
        Vector4::new(1.0, 0.0, 0.0, 0.0)
    };
    let mut cost = cost_of(&q);
    let mut lambda = 1e-3;
    let mut it = 0;
    while it < 200 {
        it += 1;
        let mut h = Matrix4::zeros();
        let mut g = Vector4::zeros();
        for s in sym {
            // q is unit here: r = qᵀSq, ∇r = 2Sq − 2 r q.
            let sq = s * q;
            let r = q.dot(&sq);
            let j = (sq - q * r) * 2.0;
            h += j * j.transpose();
            g += j * r;
        }
        let mut accepted = false;
        while lambda < 1e12 {
            let mut a = h;
            for i in 0..4 {
                a[(i, i)] += lambda * (h[(i, i)] + 1e-12);
            }
            let Some(step) = a.cholesky().map(|c| c.solve(&-g)) else {
                lambda *= 10.0;
                continue;
            };
            let cand = (q + step).normalize();
            let c = cost_of(&cand);
            if c <= cost {
                let small = step.norm() < 1e-13 || cost - c <= 1e-15 * cost.max(1e-300);
                q = cand;
                cost = c;
                lambda = (lambda * 0.1).max(1e-12);
                accepted = true;
                if small {
                    return (to_unit(&q), cost, it);
                }
                break;
            }
            lambda *= 10.0;
        }
        if !accepted {
            break;
        }
    }
    (to_unit(&q), cost, it)
}

fn to_unit(q: &Vector4<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]))
}

/// `[w, x, y, z]` of a unit quaternion.
pub fn wxyz(q: &UnitQuaternion<f64>) -> Vector4<f64> {
    Vector4::new(q.w, q.i, q.j, q.k)
}

/// The paper's whole pipeline (Algorithm 1, steps 7-9) on raw observations.
pub fn solve_paper(
    setup: &Setup,
    observations: &[Observation],
    config: &PaperConfig,
) -> Result<PaperResult, PaperError> {
    let set = prepare(setup, observations)?;
    solve_paper_prepared(&set, config)
}

/// The paper's pipeline on prepared observations.
///
/// With tool lines through points away from the origin of `{t}` (an arm without a
/// mechanical RCM), Eq. 5 depends on the rotation: the rotation (Eq. 8-10, which use only
/// the directions) is solved first, then [`translation_given_rotation`]. With every point at
/// the origin this is the paper's order and result.
pub fn solve_paper_prepared(set: &PreparedSet, config: &PaperConfig) -> Result<PaperResult, PaperError> {
    let t_rcm = linear_translation(set)?;
    let r_lin = UnitQuaternion::from_rotation_matrix(&kronecker_rotation(set)?);
    let q0 = match config.initial_quaternion {
        Some(q) => Vector4::from(q),
        None => wxyz(&r_lin),
    };
    let (q, cost, iterations) = refine_quaternion(set, &q0);
    let t =
        if set.offset_points { translation_given_rotation(set, &q.to_rotation_matrix().into_inner())? } else { t_rcm };
    Ok(PaperResult {
        pose: Isometry3::from_parts(Translation3::from(t), q),
        linear_rotation: r_lin,
        rotation_cost: cost,
        iterations,
    })
}
