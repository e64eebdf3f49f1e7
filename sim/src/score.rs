//! Scoring a detector's output against ground truth: an in-memory scenario or a ground-truth
//! file read back ([`GroundTruth`]; see `docs/simulator.md`).
//!
//! Definitions (also in `docs/trocar-detection.md`):
//! - **Insertion delay**: first sample at or after the true insertion at which the detector
//!   is inside *at the right trocar* (its fulcrum nearest to the true trocar and within
//!   `wrong_trocar_m` of the true pivot), minus the true insertion instant, seconds. Being
//!   inside somewhere else (a false detection carried over from before the insertion) does not
//!   count. Missed when that does not happen before the true extraction.
//! - **Extraction delay**: first sample at or after the true extraction at which the detector
//!   is outside, minus the true extraction instant. Missed when the detector is still inside
//!   at the next true insertion (or the end).
//! - **False detection**: an outside→inside transition while the truth is outside, or at the
//!   wrong trocar: the reported fulcrum is nearer to another trocar of the scenario than to
//!   the true one, or farther than `wrong_trocar_m` from the true pivot.
//! - **Localisation error**: distance from the reported fulcrum to the true pivot, at first
//!   detection and over every sample the detector and the truth are both inside.

use nalgebra::Vector3;

use crate::scenario::{Scenario, TrueEvent, TruthState};

/// What the detector said at one sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Detected {
    /// Inside a trocar.
    pub inside: bool,
    /// Reported fulcrum, metres, robot base frame (when inside).
    pub fulcrum_base_m: Option<Vector3<f64>>,
}

/// Scores of one run.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Score {
    /// True insertions.
    pub insertions: usize,
    /// Insertions detected before the true extraction.
    pub insertions_detected: usize,
    /// Insertion delays, seconds.
    pub insertion_delays_s: Vec<f64>,
    /// True extractions.
    pub extractions: usize,
    /// Extractions detected before the next insertion.
    pub extractions_detected: usize,
    /// Extraction delays, seconds.
    pub extraction_delays_s: Vec<f64>,
    /// False detections (outside, or wrong trocar).
    pub false_detections: usize,
    /// Localisation error at each first detection, metres.
    pub first_errors_m: Vec<f64>,
    /// Root-mean-square localisation error over all inside/inside samples, metres.
    pub rms_error_m: f64,
    /// Sample indices of the false detections.
    pub false_detection_samples: Vec<usize>,
}

/// Ground truth as the scorer needs it, sample by sample: the true state, the true pivot
/// and the true events. Implemented by an in-memory [`Scenario`] and by a ground-truth file
/// read back ([`crate::truth_file::TruthFile`]), so both are scored by the one function
/// [`score_against`].
pub trait GroundTruth {
    /// Sample period, seconds (one sample per SYNC, 0.001 s for the encoder bus).
    fn sample_period_s(&self) -> f64;
    /// Number of samples.
    fn samples(&self) -> usize;
    /// True state and true pivot (metres, robot base frame; `Some` exactly while inside) of
    /// sample `i` (`i < samples()`).
    fn truth_at(&self, i: usize) -> (TruthState, Option<Vector3<f64>>);
    /// Nominal trocar positions, metres, robot base frame.
    fn trocars_base_m(&self) -> &[[f64; 3]];
    /// Number of true events.
    fn event_count(&self) -> usize;
    /// True event `k` (`k < event_count()`), in time order.
    fn event(&self, k: usize) -> Option<TrueEvent>;
}

impl GroundTruth for Scenario {
    fn sample_period_s(&self) -> f64 {
        self.config.sample_period_s
    }
    fn samples(&self) -> usize {
        self.truth.len()
    }
    fn truth_at(&self, i: usize) -> (TruthState, Option<Vector3<f64>>) {
        self.truth.get(i).map_or((TruthState::Outside, None), |t| (t.state, t.fulcrum_base_m))
    }
    fn trocars_base_m(&self) -> &[[f64; 3]] {
        &self.config.trocars_base_m
    }
    fn event_count(&self) -> usize {
        self.events.len()
    }
    fn event(&self, k: usize) -> Option<TrueEvent> {
        self.events.get(k).copied()
    }
}

/// Scores `detected` (one entry per sample of `scenario`). `wrong_trocar_m`: a fulcrum
/// farther than this (metres) from the true pivot counts as a wrong trocar. Same as
/// [`score_against`] with the scenario as the ground truth.
pub fn score(scenario: &Scenario, detected: &[Detected], wrong_trocar_m: f64) -> Score {
    score_against(scenario, detected, wrong_trocar_m)
}

/// Scores `detected` (entry `i` is what the detector said at sample `i`) against any ground
/// truth, with the definitions at the top of this module. Samples beyond the shorter of the
/// two are ignored. `wrong_trocar_m`: a fulcrum farther than this (metres) from the true
/// pivot counts as a wrong trocar.
pub fn score_against<G: GroundTruth + ?Sized>(truth: &G, detected: &[Detected], wrong_trocar_m: f64) -> Score {
    let dt = truth.sample_period_s();
    let n = detected.len().min(truth.samples());
    let mut s = Score::default();
    let mut sq = 0.0;
    let mut sq_n = 0usize;
    for i in 0..n {
        let d = &detected[i];
        let (state, pivot) = truth.truth_at(i);
        let prev_inside = i > 0 && detected[i - 1].inside;
        if d.inside && !prev_inside {
            let wrong = match (state, pivot, d.fulcrum_base_m) {
                (TruthState::Inside { index }, Some(t), Some(f)) => {
                    (f - t).norm() > wrong_trocar_m || nearest_trocar_of(truth.trocars_base_m(), &f) != Some(index)
                }
                _ => true,
            };
            if wrong {
                s.false_detections += 1;
                s.false_detection_samples.push(i);
            }
        }
        if let (true, Some(t), Some(f)) = (d.inside, pivot, d.fulcrum_base_m) {
            sq += (f - t).norm_squared();
            sq_n += 1;
        }
    }
    s.rms_error_m = if sq_n > 0 { (sq / sq_n as f64).sqrt() } else { 0.0 };
    for k in 0..truth.event_count() {
        let Some(e) = truth.event(k) else { break };
        let end = truth.event(k + 1).map(|x| x.sample).unwrap_or(n).min(n);
        if e.insertion {
            s.insertions += 1;
            let right = |j: usize| match (detected[j].inside, detected[j].fulcrum_base_m, truth.truth_at(j)) {
                (true, Some(f), (TruthState::Inside { index }, Some(t))) => {
                    (f - t).norm() <= wrong_trocar_m && nearest_trocar_of(truth.trocars_base_m(), &f) == Some(index)
                }
                _ => false,
            };
            if let Some(j) = (e.sample..end).find(|&j| right(j)) {
                s.insertions_detected += 1;
                s.insertion_delays_s.push((j - e.sample) as f64 * dt);
                if let (Some(t), Some(f)) = (truth.truth_at(j).1, detected[j].fulcrum_base_m) {
                    s.first_errors_m.push((f - t).norm());
                }
            }
        } else {
            s.extractions += 1;
            if let Some(j) = (e.sample..end).find(|&j| !detected[j].inside) {
                s.extractions_detected += 1;
                s.extraction_delays_s.push((j - e.sample) as f64 * dt);
            }
        }
    }
    s
}

/// Index of the scenario's trocar nearest to `point` (metres, robot base frame; nominal
/// trocar positions).
pub fn nearest_trocar(scenario: &Scenario, point: &Vector3<f64>) -> Option<usize> {
    nearest_trocar_of(&scenario.config.trocars_base_m, point)
}

/// Index of the trocar of `trocars_base_m` (metres, robot base frame) nearest to `point`
/// (metres, robot base frame); `None` for an empty list.
pub fn nearest_trocar_of(trocars_base_m: &[[f64; 3]], point: &Vector3<f64>) -> Option<usize> {
    trocars_base_m
        .iter()
        .enumerate()
        .map(|(i, t)| (i, (Vector3::new(t[0], t[1], t[2]) - point).norm()))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// Mean of a slice (0 when empty).
pub fn mean(v: &[f64]) -> f64 {
    if v.is_empty() { 0.0 } else { v.iter().sum::<f64>() / v.len() as f64 }
}

/// Quantile `q` in [0, 1] of a slice by nearest rank (0 when empty).
pub fn quantile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mut w = v.to_vec();
    w.sort_by(f64::total_cmp);
    let idx = ((q * w.len() as f64).ceil() as usize).clamp(1, w.len()) - 1;
    w[idx]
}
