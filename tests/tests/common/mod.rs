//! Shared helpers: scripted instrument motions with known answers.
#![allow(dead_code)]

use estimator::trocar::LineSample;
use nalgebra::{UnitQuaternion, Vector3};

/// A line through `fulcrum` along `axis`, with the wrist `depth_m` before the fulcrum.
pub fn line_through(fulcrum: &Vector3<f64>, axis: &Vector3<f64>, depth_m: f64) -> LineSample {
    let z = axis.normalize();
    LineSample::new(fulcrum - z * depth_m, z)
}

/// Axis tilted from straight down by `tilt` radians towards azimuth `az`.
pub fn cone_axis(tilt: f64, az: f64) -> Vector3<f64> {
    Vector3::new(tilt.sin() * az.cos(), tilt.sin() * az.sin(), -tilt.cos())
}

/// Phases of a scripted motion.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Phase {
    /// Free motion far from any trocar.
    Outside,
    /// Pivoting in the trocar.
    Inside,
}

/// A scripted sequence: `cycles` × (free motion `outside_s`, pivoting about a trocar for
/// `inside_s`), at 1 kHz. Returns the lines, the phase of each sample and the trocar of each
/// inside sample.
pub fn scripted(
    trocars: &[Vector3<f64>],
    cycles: usize,
    outside_s: f64,
    inside_s: f64,
) -> (Vec<LineSample>, Vec<Phase>, Vec<Vector3<f64>>) {
    let mut lines = Vec::new();
    let mut phases = Vec::new();
    let mut fulcrums = Vec::new();
    let dt = 0.001;
    for c in 0..cycles {
        let f = trocars[c % trocars.len()];
        // Free motion: the wrist travels sideways (along y) while the axis tilts in the x-z
        // plane: consecutive lines are skew, so they never share a point.
        let n_out = (outside_s / dt) as usize;
        for i in 0..n_out {
            let t = i as f64 * dt;
            let wrist = Vector3::new(0.35, -0.15 + 0.3 * t / outside_s, 0.30 + 0.02 * (2.1 * t).cos());
            let axis = cone_axis(0.2 + 0.15 * (0.9 * t).sin(), 0.0);
            lines.push(LineSample::new(wrist, axis));
            phases.push(Phase::Outside);
            fulcrums.push(Vector3::zeros());
        }
        // Inside: pivot about f along a Lissajous cone (about 15-20 degrees per second),
        // insertion depth varying.
        let n_in = (inside_s / dt) as usize;
        for i in 0..n_in {
            let t = i as f64 * dt;
            let axis = cone_axis(0.08 + 0.2 * (0.5 - 0.5 * (2.0 * t).cos()), 0.4 + 1.5 * (1.1 * t).sin());
            let depth = 0.20 + 0.03 * (0.6 * t).sin();
            lines.push(line_through(&f, &axis, depth));
            phases.push(Phase::Inside);
            fulcrums.push(f);
        }
    }
    (lines, phases, fulcrums)
}

/// Applies a rigid motion of the base frame to a line.
pub fn moved(line: &LineSample, rot: &UnitQuaternion<f64>, trans: &Vector3<f64>) -> LineSample {
    LineSample::new(rot * line.wrist_base_m + trans, rot * line.axis_base)
}
