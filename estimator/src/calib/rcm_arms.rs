//! RCM-arm forward kinematics (ECM-like robot 1, PSM-like robot 2) and the SE(3) exponential.
//!
//! Convention (comanip's own, documented in `docs/calibration.md`; not the dVRK DH table,
//! but the same motion about the remote centre): the base frame of each arm sits at its
//! RCM, its z axis along the shaft at zero joints, pointing into the patient.
//!
//! ```text
//! ECM: F1 = Ry(q1)   F2 = F1·Rx(q2)   F3 = F2·Tz(q3)   F4 = F3·Rz(q4)     camera: F4·X
//! PSM: F1 = Ry(q1)   F2 = F1·Rx(q2)   F3 = F2·Tz(q3)
//! ```
//! `q1` yaw (rad) about the base y axis, `q2` pitch (rad) about the yawed x axis, `q3`
//! insertion (m) along the shaft, `q4` roll (rad) about the shaft. The tool axis in `{t}` is
//! `m = F2·ẑ`; it passes through the RCM (the origin of `{t}`).

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// Skew-symmetric matrix `[v]×` such that `[v]× w = v × w`.
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// SE(3) exponential `exp(δ^)` of `δ = (ρ, φ)`: `ρ` metres, `φ` radians (axis-angle).
/// Rotation `exp(φ^)`, translation `V(φ) ρ` with the left Jacobian `V` of SO(3).
pub fn se3_exp(rho: &Vector3<f64>, phi: &Vector3<f64>) -> Isometry3<f64> {
    let theta = phi.norm();
    let w = skew(phi);
    let w2 = w * w;
    let v = if theta < 1e-8 {
        Matrix3::identity() + w * 0.5 + w2 * (1.0 / 6.0)
    } else {
        let t2 = theta * theta;
        Matrix3::identity() + w * ((1.0 - theta.cos()) / t2) + w2 * ((theta - theta.sin()) / (t2 * theta))
    };
    Isometry3::from_parts(Translation3::from(v * rho), UnitQuaternion::from_scaled_axis(*phi))
}

fn rot_y(a: f64) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_axis_angle(&Vector3::y_axis(), a))
}
fn rot_x(a: f64) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_axis_angle(&Vector3::x_axis(), a))
}
fn rot_z(a: f64) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_axis_angle(&Vector3::z_axis(), a))
}
fn trans_z(d: f64) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(0.0, 0.0, d), UnitQuaternion::identity())
}

/// ECM-like arm: all four frames of `q = [yaw rad, pitch rad, insertion m, roll rad]` in the
/// arm's RCM frame `{e}` (metres). `frames[3]` is the end effector `{f}`.
pub fn ecm_frames(q: &[f64; 4]) -> [Isometry3<f64>; 4] {
    let f1 = rot_y(q[0]);
    let f2 = f1 * rot_x(q[1]);
    let f3 = f2 * trans_z(q[2]);
    let f4 = f3 * rot_z(q[3]);
    [f1, f2, f3, f4]
}

/// PSM-like arm: the three frames of `q = [yaw rad, pitch rad, insertion m]` in the arm's
/// RCM frame `{t}` (metres). `frames[2]` is the tool tip; the shaft is its z axis.
pub fn psm_frames(q: &[f64; 3]) -> [Isometry3<f64>; 3] {
    let f1 = rot_y(q[0]);
    let f2 = f1 * rot_x(q[1]);
    let f3 = f2 * trans_z(q[2]);
    [f1, f2, f3]
}

/// Unit tool-axis direction `m(θ2)` in `{t}` (from the RCM toward the tip).
pub fn psm_axis(q: &[f64; 3]) -> Vector3<f64> {
    Rotation3::from_axis_angle(&Vector3::y_axis(), q[0])
        * Rotation3::from_axis_angle(&Vector3::x_axis(), q[1])
        * Vector3::z()
}

/// Camera pose `T_e_c(θ1) = F4(θ1)·X` in `{e}` (metres) for hand-eye `X = T_f_c`.
pub fn camera_pose(q: &[f64; 4], hand_eye: &Isometry3<f64>) -> Isometry3<f64> {
    ecm_frames(q)[3] * hand_eye
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psm_axis_is_frame2_z_and_tip_is_on_it() {
        let q = [0.2, -0.3, 0.11];
        let f = psm_frames(&q);
        let m = psm_axis(&q);
        assert!((f[1].rotation * Vector3::z() - m).norm() < 1e-12);
        assert!((f[2].translation.vector - m * 0.11).norm() < 1e-12);
    }

    #[test]
    fn se3_exp_matches_rotation_and_small_angle_translation() {
        let phi = Vector3::new(0.3, -0.2, 0.1);
        let rho = Vector3::new(0.01, 0.02, -0.03);
        let t = se3_exp(&rho, &phi);
        assert!((t.rotation.scaled_axis() - phi).norm() < 1e-12);
        // Pure translation when φ = 0.
        let t0 = se3_exp(&rho, &Vector3::zeros());
        assert!((t0.translation.vector - rho).norm() < 1e-15);
        // exp(δ)·exp(−δ) = identity (one-parameter subgroup).
        let back = t * se3_exp(&-rho, &-phi);
        assert!(back.translation.vector.norm() < 1e-12);
        assert!(back.rotation.angle() < 1e-12);
    }

    #[test]
    fn ecm_insertion_moves_tip_along_shaft() {
        let a = ecm_frames(&[0.1, 0.2, 0.05, 0.3])[3];
        let b = ecm_frames(&[0.1, 0.2, 0.08, 0.3])[3];
        let shaft = a.rotation * Vector3::z();
        let d = b.translation.vector - a.translation.vector;
        assert!((d - shaft * 0.03).norm() < 1e-12);
    }
}
