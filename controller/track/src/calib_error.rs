//! The experiment where vision tracking earns its place: the camera-to-base calibration is off.
//!
//! In the simulator the encoders and the calibration are exact, so the kinematics alone put the
//! tip within half a millimetre of the rendered one and vision can only add error
//! (`docs/tracking.md`). On a robot the camera-to-base transform comes from a calibration with
//! an error of millimetres and tenths of a degree (`docs/calibration.md`: about 0.6 mm and
//! 0.1-0.2° after a 2-minute live session; the paper's pipeline several millimetres). Here the
//! tracker is given `T_b_e` (the endoscope arm's RCM frame in the tool arm's base) moved by a
//! known error, rotation about the endoscope's RCM and translation in its frame, in a random
//! direction per trial; it starts on the encoders (no start perturbation) and tracks for a
//! number of frames. The kinematics alone (the encoders through the wrong calibration) and the
//! tracker are both compared with the rendered truth in the left camera frame: what a guidance
//! module working in the camera's view would get. The paper's answer to an uncertain `g_CB` is
//! to put it in the state (Eq. 17-18, `[noise] camera`): run with `--augment` to compare.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use track::{ToolModel, TrackerConfig};

use crate::experiment::{Trial, converge, median_p95};
use crate::input::Sequence;
use crate::run::RunError;

/// One calibration error: translation (metres) and rotation (radians) of `T_b_e`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibErrorLevel {
    /// Translation error, metres (in the endoscope's RCM frame).
    pub translation_m: f64,
    /// Rotation error about the endoscope's RCM, radians.
    pub rotation_rad: f64,
}

/// The trials of one level and one tracker configuration.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CalibErrorRun {
    /// The level.
    pub level: CalibErrorLevel,
    /// `ours`, `ours + g_CB`, `paper`, …
    pub config: String,
    /// Particles.
    pub particles: usize,
    /// The trials (the `kinematics` of each is the encoders through the wrong calibration).
    pub trials: Vec<Trial>,
}

/// Why a level cannot be run.
#[derive(Debug, thiserror::Error)]
pub enum CalibErrorError {
    /// A level's error is not finite or negative.
    #[error("calibration error {0:?}: each part must be finite and ≥ 0")]
    Level(CalibErrorLevel),
    /// The tracking failed.
    #[error(transparent)]
    Run(#[from] RunError),
}

fn random_unit(r: &mut ChaCha8Rng) -> Vector3<f64> {
    loop {
        let v = Vector3::new(r.random_range(-1.0..1.0), r.random_range(-1.0..1.0), r.random_range(-1.0..1.0));
        let n = v.norm();
        if n > 0.1 && n <= 1.0 {
            return v / n;
        }
    }
}

/// `T_b_e · δ`: `ecm_in_tool_base` (metres) moved by `level` in a direction drawn from `rng`:
/// `δ` turns by `rotation_rad` about a random axis through the endoscope's RCM and moves by
/// `translation_m` along a random direction of its frame.
pub fn perturb(ecm_in_tool_base: &Isometry3<f64>, level: &CalibErrorLevel, rng: &mut ChaCha8Rng) -> Isometry3<f64> {
    let axis = random_unit(rng);
    let dir = random_unit(rng);
    let delta = Isometry3::from_parts(
        Translation3::from(dir * level.translation_m),
        UnitQuaternion::from_scaled_axis(axis * level.rotation_rad),
    );
    ecm_in_tool_base * delta
}

/// Runs `trials` trials of `frames` frames on `seq` at `level`: each with its own random
/// direction of the error, started on the encoders, the camera from the moved `T_b_e`. Trials
/// start at random frames with the instrument visible in both eyes (`min_px` pixels each) for
/// the whole trial (as [`converge`]). `progress` is called after each tracked frame.
#[allow(clippy::too_many_arguments, reason = "an experiment's parameters, each named at the call")]
pub fn run_level(
    seq: &Sequence,
    label: &str,
    model: &ToolModel,
    cfg: TrackerConfig,
    level: CalibErrorLevel,
    trials: usize,
    frames: usize,
    seed: u64,
    min_px: u64,
    progress: &dyn Fn(),
) -> Result<Vec<Trial>, CalibErrorError> {
    let ok = |v: f64| v.is_finite() && v >= 0.0;
    if !(ok(level.translation_m) && ok(level.rotation_rad)) {
        return Err(CalibErrorError::Level(level));
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xCA11_B0FF);
    let mut out = Vec::with_capacity(trials);
    for t in 0..trials {
        let mut moved = seq.clone();
        moved.ecm_in_tool_base = perturb(&seq.ecm_in_tool_base, &level, &mut rng);
        // One trial per call, its start drawn from its own seed.
        let trial_seed = seed.wrapping_mul(7919).wrapping_add(t as u64);
        let mut one = converge(&moved, label, model, cfg, 1, frames, 0.0, 0.0, trial_seed, min_px, 0.0, progress)?;
        out.append(&mut one);
    }
    Ok(out)
}

/// A run's figures: the kinematics and the tracker against the truth over the second half of
/// every trial's frames (the tracker has had half the trial to settle), medians and p95.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CalibErrorSummary {
    /// The level, millimetres and degrees.
    pub error_mm: f64,
    /// See `error_mm`.
    pub error_deg: f64,
    /// The configuration.
    pub config: String,
    /// Trials.
    pub trials: usize,
    /// Frames counted (second halves).
    pub frames: usize,
    /// Kinematics alone: tip position error median and p95, millimetres.
    pub kinematics_mm: (f64, f64),
    /// Kinematics alone: orientation error median and p95, degrees.
    pub kinematics_deg: (f64, f64),
    /// Tracker (frames with a pose): tip position error median and p95, millimetres.
    pub tracker_mm: (f64, f64),
    /// Tracker: orientation error median and p95, degrees.
    pub tracker_deg: (f64, f64),
    /// Second-half frames without a pose (LOST).
    pub lost: usize,
    /// Second-half frames where the tracker's tip is closer to the truth than the kinematics'.
    pub tracker_closer: usize,
}

/// The figures of `run` (see [`CalibErrorSummary`]).
pub fn summarise(run: &CalibErrorRun) -> CalibErrorSummary {
    let (mut km, mut kd, mut tm, mut td) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let (mut frames, mut lost, mut closer) = (0, 0, 0);
    for t in &run.trials {
        let half = t.errors.len() / 2;
        for (e, k) in t.errors.iter().zip(&t.kinematics).skip(half) {
            frames += 1;
            if let Some((p, a)) = k {
                km.push(*p);
                kd.push(*a);
            }
            match e {
                Some((p, a)) => {
                    tm.push(*p);
                    td.push(*a);
                    if k.is_some_and(|(kp, _)| p < &kp) {
                        closer += 1;
                    }
                }
                None => lost += 1,
            }
        }
    }
    CalibErrorSummary {
        error_mm: run.level.translation_m * 1e3,
        error_deg: run.level.rotation_rad.to_degrees(),
        config: run.config.clone(),
        trials: run.trials.len(),
        frames,
        kinematics_mm: median_p95(&mut km),
        kinematics_deg: median_p95(&mut kd),
        tracker_mm: median_p95(&mut tm),
        tracker_deg: median_p95(&mut td),
        lost,
        tracker_closer: closer,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_perturbation_has_the_level_s_size_about_the_rcm() {
        let t_b_e = Isometry3::from_parts(
            Translation3::new(0.29, 0.0, 0.16),
            UnitQuaternion::from_euler_angles(0.3, -0.2, 1.0),
        );
        let level = CalibErrorLevel { translation_m: 0.005, rotation_rad: 2f64.to_radians() };
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..20 {
            let moved = perturb(&t_b_e, &level, &mut rng);
            let delta = t_b_e.inverse() * moved;
            assert!((delta.translation.vector.norm() - 0.005).abs() < 1e-12);
            assert!((delta.rotation.angle() - 2f64.to_radians()).abs() < 1e-12);
        }
        let zero = CalibErrorLevel { translation_m: 0.0, rotation_rad: 0.0 };
        let same = perturb(&t_b_e, &zero, &mut rng);
        assert!((same.translation.vector - t_b_e.translation.vector).norm() < 1e-15);
    }

    #[test]
    fn the_summary_counts_second_halves_and_who_is_closer() {
        let trial = Trial {
            sequence: "s".into(),
            first: 0,
            initial: (0.0, 0.0),
            errors: vec![Some((9.0, 9.0)), Some((9.0, 9.0)), Some((1.0, 0.5)), None],
            status: vec!["TRACKING".into(); 4],
            converged_at: None,
            step_ms: 1.0,
            kinematics: vec![Some((3.0, 1.0)); 4],
            reinitialised_at: None,
            reseeded_at: None,
            inlier_share: Vec::new(),
            axis_detected: Vec::new(),
            reseed_share: Vec::new(),
        };
        let run = CalibErrorRun {
            level: CalibErrorLevel { translation_m: 0.002, rotation_rad: 0.01 },
            config: "ours".into(),
            particles: 10,
            trials: vec![trial],
        };
        let s = summarise(&run);
        assert_eq!((s.frames, s.lost, s.tracker_closer), (2, 1, 1));
        assert_eq!(s.tracker_mm.0, 1.0);
        assert_eq!(s.kinematics_mm.0, 3.0);
        assert!((s.error_mm - 2.0).abs() < 1e-12);
    }
}
