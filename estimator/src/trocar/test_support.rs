//! Test helpers shared by the detector's unit tests: scripted instrument motions with known
//! answers (lines through a fulcrum, cones of directions, free motion between trocars), and a
//! runner that checks every state change of a scripted sequence. Compiled for tests only.

use std::vec::Vec;

use nalgebra::{UnitQuaternion, Vector3};

use super::{Detector, DetectorConfig, DetectorMode, Estimate, LineSample};

/// Both detector modes, for tests that hold for each.
pub(crate) const MODES: [DetectorMode; 2] = [DetectorMode::Paper, DetectorMode::Fast];

/// A detector of `mode` with every other setting at its default.
pub(crate) fn detector(mode: DetectorMode) -> Detector {
    Detector::new(&DetectorConfig { mode, ..Default::default() }).unwrap()
}

/// Asserts that no output field of `e` is NaN or Inf.
pub(crate) fn assert_finite(e: &Estimate) {
    if let Some(f) = e.fulcrum_base_m {
        assert!(f.iter().all(|v| v.is_finite()));
    }
    if let Some(fit) = e.fit {
        assert!(fit.point_base_m.iter().all(|v| v.is_finite()));
        assert!(fit.residual_m.is_finite() && fit.conditioning.is_finite() && fit.std_m.is_finite());
    }
}

/// A line through `fulcrum` (metres, base frame) along `axis`, with the wrist `depth_m`
/// before the fulcrum.
pub(crate) fn line_through(fulcrum: &Vector3<f64>, axis: &Vector3<f64>, depth_m: f64) -> LineSample {
    let z = axis.normalize();
    LineSample::new(fulcrum - z * depth_m, z)
}

/// Axis tilted from straight down by `tilt` radians towards azimuth `az` (radians).
pub(crate) fn cone_axis(tilt: f64, az: f64) -> Vector3<f64> {
    Vector3::new(tilt.sin() * az.cos(), tilt.sin() * az.sin(), -tilt.cos())
}

/// Phases of a scripted motion.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Phase {
    /// Free motion far from any trocar.
    Outside,
    /// Pivoting in the trocar.
    Inside,
}

/// A scripted sequence: `cycles` × (free motion `outside_s`, pivoting about a trocar for
/// `inside_s`), at 1 kHz. Returns the lines, the phase of each sample and the trocar of each
/// inside sample.
pub(crate) fn scripted(
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
pub(crate) fn moved(line: &LineSample, rot: &UnitQuaternion<f64>, trans: &Vector3<f64>) -> LineSample {
    LineSample::new(rot * line.wrist_base_m + trans, rot * line.axis_base)
}

/// Insertion and extraction delays of a scripted run, seconds.
pub(crate) struct Delays {
    /// From the start of each inside phase to the detection.
    pub(crate) insertion_s: Vec<f64>,
    /// From the start of each outside phase (but the first) to the extraction.
    pub(crate) extraction_s: Vec<f64>,
}

/// Runs a scripted sequence (three trocars, six cycles) and checks every state change;
/// returns the delays.
pub(crate) fn run_scripted(cfg: &DetectorConfig, max_delay_s: f64) -> Delays {
    let trocars = [Vector3::new(0.42, -0.08, 0.02), Vector3::new(0.48, 0.06, 0.04), Vector3::new(0.36, 0.0, 0.0)];
    let (lines, phases, fulcrums) = scripted(&trocars, 6, 3.0, 8.0);
    let mut d = Detector::new(cfg).unwrap();
    let mut delays = Delays { insertion_s: Vec::new(), extraction_s: Vec::new() };
    let mut phase_start = 0;
    let mut seen_change = false;
    for (i, l) in lines.iter().enumerate() {
        if i > 0 && phases[i] != phases[i - 1] {
            phase_start = i;
            seen_change = false;
        }
        let e = d.step(l);
        let age_s = (i - phase_start) as f64 * 0.001;
        match phases[i] {
            Phase::Inside => {
                if e.state.is_inside() {
                    let err = (e.fulcrum_base_m.unwrap() - fulcrums[i]).norm();
                    assert!(err < 0.005, "{:?}: fulcrum {err} m from the trocar at sample {i}", cfg.mode);
                    if !seen_change {
                        delays.insertion_s.push(age_s);
                        seen_change = true;
                    }
                } else {
                    assert!(!seen_change, "{:?}: spurious extraction at sample {i}", cfg.mode);
                    assert!(age_s < max_delay_s, "{:?}: insertion not detected within {max_delay_s} s", cfg.mode);
                }
            }
            Phase::Outside => {
                if e.state.is_inside() {
                    assert!(!seen_change, "{:?}: false detection while outside at sample {i}", cfg.mode);
                    // Still inside from the previous cycle: allowed only at the start.
                    assert!(phase_start > 0, "{:?}: inside at start-up", cfg.mode);
                    assert!(age_s < max_delay_s, "{:?}: extraction not detected within {max_delay_s} s", cfg.mode);
                } else if !seen_change {
                    if phase_start > 0 {
                        delays.extraction_s.push(age_s);
                    }
                    seen_change = true;
                }
            }
        }
    }
    assert_eq!(delays.insertion_s.len(), 6, "{:?}: every insertion detected", cfg.mode);
    assert_eq!(delays.extraction_s.len(), 5, "{:?}: every extraction detected", cfg.mode);
    delays
}

/// Arithmetic mean of `v`.
pub(crate) fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

/// A two-direction swing (a cone of directions) about `f` for `seconds`, the point `f` at
/// `depth(t)` metres from the wrist along the shaft.
pub(crate) fn cone_swing(f: &Vector3<f64>, seconds: f64, depth: impl Fn(f64) -> f64) -> Vec<LineSample> {
    (0..(seconds * 1000.0) as usize)
        .map(|i| {
            let t = i as f64 * 1e-3;
            let pitch = 0.15 * (2.0 * core::f64::consts::PI * 0.7 * t).sin();
            let yaw = 0.12 * (2.0 * core::f64::consts::PI * 0.45 * t).sin();
            let axis = (UnitQuaternion::from_euler_angles(pitch, yaw, 0.0) * Vector3::new(0.0, 0.0, -1.0)).normalize();
            line_through(f, &axis, depth(t))
        })
        .collect()
}

/// Steps `d` through `lines`; true if any estimate was inside.
pub(crate) fn ever_inside(d: &mut Detector, lines: &[LineSample]) -> bool {
    lines.iter().fold(false, |acc, l| d.step(l).state.is_inside() | acc)
}
