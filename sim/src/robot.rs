//! The simulated Achilles arm: inverse kinematics and the arm's true (miscalibrated)
//! parameters.
//!
//! Frames and units: every position is in metres in the robot base frame, every axis a unit
//! vector in the robot base frame, every angle in radians. Joint angles are *measured*
//! angles `q_i` as in [`estimator::kinematics`] (the DH angle is
//! `θ_i = sign_i · q_i + zero_offset_i + theta_offset_i`).
//!
//! The instrument line is `(P, z)`: P the wrist centre (translation of the last DH frame) and
//! z the instrument axis (z axis of the last DH frame). The roll about the instrument axis
//! does not change the line; the inverse kinematics takes it as the measured angle of
//! joint 6 and solves joints 1-5 for the line.
//!
//! The solver is a damped Gauss-Newton (Levenberg-Marquardt) iteration on joints 1-5 with
//! an analytical Jacobian, so it works for any (perturbed) DH table. It is seeded either by
//! the previous solution (continuous trajectories, see [`IkTracker`]) or by a closed form
//! for the default geometry ([`closed_form_guess`]).
//!
//! [`SimulatedArm`] holds the *true* parameters of the simulated robot: the nominal
//! configuration (the one the controller believes) plus a [`ModelError`]. The simulator
//! solves the inverse kinematics on the true parameters, so the controller's nominal forward
//! kinematics sees the calibration error.

use core::f64::consts::FRAC_PI_2;

use estimator::kinematics::{Achilles, AchillesConfig, DhRow, ForwardError, JOINTS, KinematicsConfigError, WristPose};
use estimator::trocar::LineSample;
use nalgebra::{Isometry3, Matrix5, SMatrix, Translation3, UnitQuaternion, Vector3, Vector5, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Convergence tolerance of the inverse kinematics: wrist position error (metres) and axis
/// error (norm of the difference of unit vectors, about radians).
pub const IK_TOLERANCE: f64 = 1e-12;

/// Maximum Levenberg-Marquardt iterations per attempt.
pub const IK_MAX_ITERATIONS: usize = 200;

/// Largest joint step per iteration, radians (keeps the solver on the seed's branch).
const MAX_STEP_RAD: f64 = 0.3;

/// Why the inverse kinematics found no joint angles.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum IkError {
    /// The wrist, axis or roll is NaN or infinite.
    #[error("inverse kinematics: target wrist, axis or roll is not finite")]
    NonFinite,
    /// The axis has (nearly) zero length.
    #[error("inverse kinematics: target axis has zero length")]
    ZeroAxis,
    /// The solver did not reach the target: usually an unreachable line.
    #[error(
        "inverse kinematics did not converge after {iterations} iterations: wrist off by {position_error_m:e} m, \
         axis off by {axis_error:e} (unreachable line?)"
    )]
    NotConverged {
        /// Iterations run (all attempts).
        iterations: usize,
        /// Remaining wrist position error of the best attempt, metres.
        position_error_m: f64,
        /// Remaining axis error of the best attempt (norm of the difference of unit vectors).
        axis_error: f64,
    },
}

/// Calibration error of a simulated arm: what the true arm differs by from the nominal
/// configuration.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ModelError {
    /// Per-link errors of the DH lengths `[d_m, a_m]` of joints 1..6, metres (added to the
    /// nominal values).
    pub link_length_errors_m: [[f64; 2]; JOINTS],
    /// Per-joint errors of the DH angle offsets of joints 1..6, radians (added to
    /// `theta_offset_rad`).
    pub joint_offset_errors_rad: [f64; JOINTS],
}

impl ModelError {
    /// No error: the true arm is the nominal arm.
    pub fn zero() -> Self {
        Self::default()
    }

    /// A deterministic random error from `seed`: every length error uniform in
    /// `±max_length_m` (metres), every joint offset error uniform in `±max_offset_rad`
    /// (radians). Non-finite or negative bounds are treated as 0.
    pub fn from_seed(seed: u64, max_length_m: f64, max_offset_rad: f64) -> Self {
        let bound = |b: f64| if b.is_finite() && b > 0.0 { b } else { 0.0 };
        let (ml, mo) = (bound(max_length_m), bound(max_offset_rad));
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut uniform = |b: f64| if b > 0.0 { rng.random_range(-b..=b) } else { 0.0 };
        let mut e = Self::default();
        for i in 0..JOINTS {
            e.link_length_errors_m[i] = [uniform(ml), uniform(ml)];
            e.joint_offset_errors_rad[i] = uniform(mo);
        }
        e
    }

    /// The true configuration: `nominal` with this error added.
    pub fn apply(&self, nominal: &AchillesConfig) -> AchillesConfig {
        let mut c = *nominal;
        for i in 0..JOINTS {
            c.dh[i].d_m += self.link_length_errors_m[i][0];
            c.dh[i].a_m += self.link_length_errors_m[i][1];
            c.dh[i].theta_offset_rad += self.joint_offset_errors_rad[i];
        }
        c
    }
}

/// Pose of DH frame `i+1` relative to frame `i` (same formula as the estimator's forward
/// kinematics: `Rz(θ) · Tz(d) · Tx(a) · Rx(α)`), metres.
fn link(row: &DhRow, theta_rad: f64) -> Isometry3<f64> {
    let rz = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), theta_rad);
    let rx = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), row.alpha_rad);
    let t = rz * Vector3::new(row.a_m, 0.0, row.d_m);
    Isometry3::from_parts(Translation3::from(t), rz * rx)
}

/// Poses of DH frames 0..=6 in the robot base frame (frame 0 is the base).
fn frames(arm: &Achilles, q_rad: &[f64; JOINTS]) -> [Isometry3<f64>; JOINTS + 1] {
    let mut out = [Isometry3::identity(); JOINTS + 1];
    for i in 0..JOINTS {
        out[i + 1] = out[i] * link(&arm.config().dh[i], arm.dh_angle(i, q_rad[i]));
    }
    out
}

/// Errors (wrist metres, axis) of a pose against a target line.
fn line_errors(pose: &WristPose, wrist_m: &Vector3<f64>, axis: &Vector3<f64>) -> (f64, f64) {
    ((pose.wrist_base_m - wrist_m).norm(), (pose.axis_base - axis).norm())
}

/// A starting point for the inverse kinematics from the closed-form solution of the
/// *default* geometry (shoulder height `d_1`, upper arm `a_2`, forearm `d_4`, spherical
/// wrist), elbow up, `θ_5` in `[0, π]`. Exact for the default table, approximate for a
/// perturbed one. `wrist_m`: wrist centre P, metres, base frame; `axis`: instrument axis
/// (normalised here), base frame; `roll_rad`: measured angle of joint 6. Returns measured
/// joint angles, radians; always finite for finite input (out-of-reach points are clamped
/// to the arm's reach).
pub fn closed_form_guess(arm: &Achilles, wrist_m: &Vector3<f64>, axis: &Vector3<f64>, roll_rad: f64) -> [f64; JOINTS] {
    let dh = &arm.config().dh;
    let (d1, l1, l2) = (dh[0].d_m, dh[1].a_m, dh[3].d_m);
    let t1 = wrist_m.y.atan2(wrist_m.x);
    let r = wrist_m.x.hypot(wrist_m.y);
    let h = wrist_m.z - d1;
    let denom = 2.0 * l1 * l2;
    let cos_phi =
        if denom.abs() > 1e-12 { ((r * r + h * h - l1 * l1 - l2 * l2) / denom).clamp(-1.0, 1.0) } else { 0.0 };
    let phi = -cos_phi.acos(); // elbow up: the forearm bends down from the upper arm
    let t2 = h.atan2(r) - (l2 * phi.sin()).atan2(l1 + l2 * phi.cos());
    let t3 = phi + FRAC_PI_2;
    // Orientation of frame 3 for the default twists (α1 = α3 = +90°, α2 = 0).
    let r3 = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), t1)
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), FRAC_PI_2)
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), t2 + t3)
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), FRAC_PI_2);
    let n = axis.norm();
    let z3 = if n > 0.0 { r3.inverse() * (axis / n) } else { Vector3::z() };
    // z in frame 3 is (sin θ5 cos θ4, sin θ5 sin θ4, cos θ5) for the default wrist.
    let t5 = z3.z.clamp(-1.0, 1.0).acos();
    let t4 = if z3.x.hypot(z3.y) > 1e-12 { z3.y.atan2(z3.x) } else { 0.0 };
    let thetas = [t1, t2, t3, t4, t5];
    let mut q = [0.0; JOINTS];
    for (i, &t) in thetas.iter().enumerate() {
        q[i] = arm.measured_angle(i, t);
    }
    q[5] = roll_rad;
    q
}

/// Result of one Levenberg-Marquardt attempt.
enum Attempt {
    Converged([f64; JOINTS], usize),
    Failed { iterations: usize, position_error_m: f64, axis_error: f64 },
}

/// Damped Gauss-Newton on joints 1-5 from `q0` (joint 6 fixed).
fn solve_from(arm: &Achilles, wrist_m: &Vector3<f64>, axis: &Vector3<f64>, q0: [f64; JOINTS]) -> Attempt {
    let residual = |q: &[f64; JOINTS]| -> Option<(Vector6<f64>, [Isometry3<f64>; JOINTS + 1])> {
        if q.iter().any(|v| !v.is_finite()) {
            return None;
        }
        let f = frames(arm, q);
        let p = f[JOINTS].translation.vector;
        let z = f[JOINTS].rotation * Vector3::z();
        let dp = p - wrist_m;
        let dz = z - axis;
        Some((Vector6::new(dp.x, dp.y, dp.z, dz.x, dz.y, dz.z), f))
    };
    let mut q = q0;
    let Some((mut r, mut f)) = residual(&q) else {
        return Attempt::Failed { iterations: 0, position_error_m: f64::INFINITY, axis_error: f64::INFINITY };
    };
    let mut lambda = 1e-6;
    let mut iterations = 0;
    while iterations < IK_MAX_ITERATIONS {
        let pos_err = r.fixed_rows::<3>(0).norm();
        let axis_err = r.fixed_rows::<3>(3).norm();
        if pos_err < IK_TOLERANCE && axis_err < IK_TOLERANCE {
            return Attempt::Converged(q, iterations);
        }
        iterations += 1;
        // Analytical Jacobian: dθ_i/dq_i = sign_i; joint i turns about z of frame i-1.
        let p = f[JOINTS].translation.vector;
        let z = f[JOINTS].rotation * Vector3::z();
        let mut jac = SMatrix::<f64, 6, 5>::zeros();
        for (i, (frame, joint)) in f.iter().zip(&arm.config().joints).take(5).enumerate() {
            let s = joint.sign;
            let zi = frame.rotation * Vector3::z();
            let oi = frame.translation.vector;
            let dp = zi.cross(&(p - oi)) * s;
            let dz = zi.cross(&z) * s;
            jac.set_column(i, &Vector6::new(dp.x, dp.y, dp.z, dz.x, dz.y, dz.z));
        }
        let jtj: Matrix5<f64> = jac.transpose() * jac;
        let g: Vector5<f64> = jac.transpose() * r;
        let cost = r.norm_squared();
        let mut accepted = false;
        while lambda < 1e10 {
            let a = jtj + Matrix5::identity() * lambda;
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let mut step = chol.solve(&g);
            let max = step.amax();
            if max > MAX_STEP_RAD {
                step *= MAX_STEP_RAD / max;
            }
            let mut q_new = q;
            for i in 0..5 {
                q_new[i] -= step[i];
            }
            match residual(&q_new) {
                Some((r_new, f_new)) if r_new.norm_squared() < cost => {
                    q = q_new;
                    r = r_new;
                    f = f_new;
                    lambda = (lambda / 10.0).max(1e-15);
                    accepted = true;
                    break;
                }
                _ => lambda *= 10.0,
            }
        }
        if !accepted {
            break;
        }
    }
    let pos_err = r.fixed_rows::<3>(0).norm();
    let axis_err = r.fixed_rows::<3>(3).norm();
    if pos_err < IK_TOLERANCE && axis_err < IK_TOLERANCE {
        return Attempt::Converged(q, iterations);
    }
    Attempt::Failed { iterations, position_error_m: pos_err, axis_error: axis_err }
}

/// Inverse kinematics of `arm`: measured joint angles (radians) whose forward kinematics
/// puts the wrist centre at `wrist_m` (metres, base frame) and the instrument axis along
/// `axis` (base frame; normalised here), with joint 6 at the measured angle `roll_rad`.
///
/// Starts from `seed` (e.g. the previous sample's solution) when given, then, if that
/// fails, from [`closed_form_guess`]. The result reproduces the line to [`IK_TOLERANCE`]
/// (checked against [`Achilles::forward`]).
pub fn inverse(
    arm: &Achilles,
    wrist_m: &Vector3<f64>,
    axis: &Vector3<f64>,
    roll_rad: f64,
    seed: Option<&[f64; JOINTS]>,
) -> Result<[f64; JOINTS], IkError> {
    if wrist_m.iter().chain(axis.iter()).any(|v| !v.is_finite()) || !roll_rad.is_finite() {
        return Err(IkError::NonFinite);
    }
    let n = axis.norm();
    if n < 1e-9 {
        return Err(IkError::ZeroAxis);
    }
    let axis = axis / n;
    let mut starts: heapless::Vec<[f64; JOINTS], 2> = heapless::Vec::new();
    if let Some(s) = seed.filter(|s| s.iter().all(|v| v.is_finite())) {
        let mut s = *s;
        s[5] = roll_rad;
        let _ = starts.push(s);
    }
    let _ = starts.push(closed_form_guess(arm, wrist_m, &axis, roll_rad));
    let mut total = 0;
    let mut best = (f64::INFINITY, f64::INFINITY);
    for q0 in starts {
        match solve_from(arm, wrist_m, &axis, q0) {
            Attempt::Converged(q, it) => {
                total += it;
                // Cross-check with the estimator's own forward kinematics.
                if let Ok(pose) = arm.forward(&q) {
                    let (pe, ae) = line_errors(&pose, wrist_m, &axis);
                    if pe < 10.0 * IK_TOLERANCE && ae < 10.0 * IK_TOLERANCE {
                        return Ok(q);
                    }
                    best = (pe, ae);
                }
            }
            Attempt::Failed { iterations, position_error_m, axis_error } => {
                total += iterations;
                if position_error_m + axis_error < best.0 + best.1 {
                    best = (position_error_m, axis_error);
                }
            }
        }
    }
    Err(IkError::NotConverged { iterations: total, position_error_m: best.0, axis_error: best.1 })
}

/// The simulated robot: the nominal configuration the controller believes in, the true
/// configuration (nominal plus [`ModelError`]) the simulation moves, and its inverse
/// kinematics on the true parameters.
#[derive(Clone, Copy, Debug)]
pub struct SimulatedArm {
    nominal: AchillesConfig,
    error: ModelError,
    truth: Achilles,
}

impl SimulatedArm {
    /// Builds the arm from the nominal configuration and its calibration error; fails if
    /// the true configuration is invalid (non-finite or implausible values).
    pub fn new(nominal: &AchillesConfig, error: ModelError) -> Result<Self, KinematicsConfigError> {
        nominal.validate()?;
        let truth = Achilles::new(&error.apply(nominal))?;
        Ok(Self { nominal: *nominal, error, truth })
    }

    /// An arm with no calibration error.
    pub fn exact(nominal: &AchillesConfig) -> Result<Self, KinematicsConfigError> {
        Self::new(nominal, ModelError::zero())
    }

    /// The configuration the controller believes in.
    pub fn nominal(&self) -> &AchillesConfig {
        &self.nominal
    }

    /// The calibration error of this arm.
    pub fn model_error(&self) -> &ModelError {
        &self.error
    }

    /// The true kinematic model of the simulated robot.
    pub fn true_arm(&self) -> &Achilles {
        &self.truth
    }

    /// True forward kinematics: the line (metres, base frame) the instrument really has for
    /// measured joint angles `q_rad` (radians).
    pub fn forward(&self, q_rad: &[f64; JOINTS]) -> Result<WristPose, ForwardError> {
        self.truth.forward(q_rad)
    }

    /// Inverse kinematics on the true parameters; see [`inverse`]. `line`: wrist centre
    /// (metres) and instrument axis, base frame; `roll_rad`: measured angle of joint 6;
    /// `seed`: previous solution (radians), if any. Returns measured joint angles, radians.
    pub fn inverse(
        &self,
        line: &LineSample,
        roll_rad: f64,
        seed: Option<&[f64; JOINTS]>,
    ) -> Result<[f64; JOINTS], IkError> {
        inverse(&self.truth, &line.wrist_base_m, &line.axis_base, roll_rad, seed)
    }
}

/// Inverse kinematics along a continuous trajectory: each solution seeds the next, so the
/// joints stay on one branch and move continuously.
#[derive(Clone, Copy, Debug)]
pub struct IkTracker {
    arm: SimulatedArm,
    last: Option<[f64; JOINTS]>,
}

impl IkTracker {
    /// A tracker on `arm` with no previous solution.
    pub fn new(arm: SimulatedArm) -> Self {
        Self { arm, last: None }
    }

    /// The arm being tracked.
    pub fn arm(&self) -> &SimulatedArm {
        &self.arm
    }

    /// The last solution, measured joint angles in radians.
    pub fn last(&self) -> Option<&[f64; JOINTS]> {
        self.last.as_ref()
    }

    /// Forgets the previous solution (the next call starts from the closed-form guess).
    pub fn reset(&mut self) {
        self.last = None;
    }

    /// Joint angles (radians) for the next line (metres, base frame) and roll (radians,
    /// measured angle of joint 6), seeded by the previous solution. On error the previous
    /// solution is kept.
    pub fn solve(&mut self, line: &LineSample, roll_rad: f64) -> Result<[f64; JOINTS], IkError> {
        let q = self.arm.inverse(line, roll_rad, self.last.as_ref())?;
        self.last = Some(q);
        Ok(q)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::{ScenarioConfig, generate};

    fn random_line(rng: &mut ChaCha8Rng) -> (Vector3<f64>, Vector3<f64>) {
        let trocar =
            Vector3::new(rng.random_range(0.36..0.50), rng.random_range(-0.1..0.1), rng.random_range(0.0..0.05));
        let tilt = rng.random_range(0.0_f64..30.0).to_radians();
        let az = rng.random_range(0.0..std::f64::consts::TAU);
        let axis = Vector3::new(tilt.sin() * az.cos(), tilt.sin() * az.sin(), -tilt.cos());
        let s = rng.random_range(0.15..0.35);
        (trocar - axis * s, axis)
    }

    fn shoulder_distance(p: &Vector3<f64>) -> f64 {
        (p - Vector3::new(0.0, 0.0, 0.35)).norm()
    }

    fn check_round_trip(arm: &SimulatedArm, n: usize, seed: u64) -> usize {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut tested = 0;
        while tested < n {
            let (p, z) = random_line(&mut rng);
            if shoulder_distance(&p) > 0.58 {
                continue; // beyond the reach of the arm (0.60 m from the shoulder)
            }
            tested += 1;
            let roll = rng.random_range(-3.0..3.0);
            let q = arm.inverse(&LineSample::new(p, z), roll, None).unwrap();
            let pose = arm.forward(&q).unwrap();
            assert!((pose.wrist_base_m - p).norm() < 1e-9, "wrist {} vs {}", pose.wrist_base_m, p);
            assert!((pose.axis_base - z).norm() < 1e-9, "axis {} vs {}", pose.axis_base, z);
            assert_eq!(q[5], roll);
        }
        tested
    }

    #[test]
    fn round_trip_default_geometry() {
        let arm = SimulatedArm::exact(&AchillesConfig::default()).unwrap();
        assert_eq!(check_round_trip(&arm, 500, 7), 500);
    }

    #[test]
    fn round_trip_perturbed_geometry() {
        for seed in 0..5 {
            let err = ModelError::from_seed(seed, 0.002, 0.01);
            let arm = SimulatedArm::new(&AchillesConfig::default(), err).unwrap();
            check_round_trip(&arm, 100, 100 + seed);
        }
    }

    #[test]
    fn closed_form_guess_is_exact_for_default_geometry() {
        let arm = Achilles::new(&AchillesConfig::default()).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..100 {
            let (p, z) = random_line(&mut rng);
            if shoulder_distance(&p) > 0.58 {
                continue;
            }
            let pose = arm.forward(&closed_form_guess(&arm, &p, &z, 0.2)).unwrap();
            assert!((pose.wrist_base_m - p).norm() < 1e-9);
            assert!((pose.axis_base - z).norm() < 1e-9);
        }
    }

    #[test]
    fn model_error_is_deterministic_and_bounded() {
        let a = ModelError::from_seed(42, 0.001, 0.005);
        assert_eq!(a, ModelError::from_seed(42, 0.001, 0.005));
        assert_ne!(a, ModelError::from_seed(43, 0.001, 0.005));
        assert!(a.link_length_errors_m.iter().flatten().all(|e| e.abs() <= 0.001));
        assert!(a.joint_offset_errors_rad.iter().all(|e| e.abs() <= 0.005));
        assert_eq!(ModelError::from_seed(1, f64::NAN, -1.0), ModelError::zero());
    }

    #[test]
    fn nominal_forward_sees_the_calibration_error() {
        let nominal = AchillesConfig::default();
        let arm = SimulatedArm::new(&nominal, ModelError::from_seed(9, 0.001, 0.005)).unwrap();
        let p = Vector3::new(0.42, 0.0, 0.25);
        let z = Vector3::new(0.0, 0.0, -1.0);
        let q = arm.inverse(&LineSample::new(p, z), 0.0, None).unwrap();
        let seen = Achilles::new(&nominal).unwrap().forward(&q).unwrap();
        let off = (seen.wrist_base_m - p).norm();
        assert!(off > 1e-4 && off < 0.02, "nominal FK off by {off} m");
    }

    #[test]
    fn continuity_along_scenario_truth() {
        let sc = generate(&ScenarioConfig { cycles: 2, ..Default::default() });
        let arm = SimulatedArm::new(&AchillesConfig::default(), ModelError::from_seed(5, 0.001, 0.003)).unwrap();
        let mut tracker = IkTracker::new(arm);
        let mut prev: Option<([f64; 6], LineSample)> = None;
        let mut total_jump = 0.0;
        let mut max_jump: f64 = 0.0;
        for t in &sc.truth {
            let q = tracker.solve(&t.line, 0.0).unwrap();
            let pose = arm.forward(&q).unwrap();
            assert!((pose.wrist_base_m - t.line.wrist_base_m).norm() < 1e-9);
            assert!((pose.axis_base - t.line.axis_base).norm() < 1e-9);
            if let Some((pq, pl)) = prev {
                let jump: f64 = q.iter().zip(&pq).map(|(a, b)| (a - b).abs()).sum();
                // Change of the line: wrist in units of 0.1 m, plus axis.
                let dl =
                    (t.line.wrist_base_m - pl.wrist_base_m).norm() / 0.1 + (t.line.axis_base - pl.axis_base).norm();
                // Joint speed is bounded by the line speed, amplified near the wrist
                // singularity (θ5 → 0) by 1 / sin θ5; a branch flip would break this.
                let s5 = arm.true_arm().dh_angle(4, q[4]).sin().abs().max(1e-3);
                assert!(
                    jump <= (3.0 + 1.0 / s5) * dl + 1e-9,
                    "t = {} s: joint jump {jump} rad for line change {dl}",
                    t.t_s
                );
                total_jump += jump;
                max_jump = max_jump.max(jump);
            }
            prev = Some((q, t.line));
        }
        // The scenario's truth itself has a few jumps of some centimetres (see the ratio
        // check above); no branch flip (≈ π) happens.
        assert!(max_jump < 1.0, "max joint jump per sample {max_jump} rad");
        assert!(total_jump < 100.0, "total joint path {total_jump} rad");
    }

    #[test]
    fn unreachable_point_is_an_error() {
        let arm = SimulatedArm::exact(&AchillesConfig::default()).unwrap();
        let far = LineSample::new(Vector3::new(2.0, 0.0, 0.0), Vector3::new(0.0, 0.0, -1.0));
        assert!(matches!(arm.inverse(&far, 0.0, None), Err(IkError::NotConverged { .. })));
        let bad = LineSample::new(Vector3::new(f64::NAN, 0.0, 0.0), Vector3::new(0.0, 0.0, -1.0));
        assert_eq!(arm.inverse(&bad, 0.0, None), Err(IkError::NonFinite));
        let zero = LineSample::new(Vector3::new(0.4, 0.0, 0.2), Vector3::zeros());
        assert_eq!(arm.inverse(&zero, 0.0, None), Err(IkError::ZeroAxis));
    }
}
