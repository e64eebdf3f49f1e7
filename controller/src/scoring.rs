//! Scoring a candump replay against the simulator's ground truth (`truth.jsonl`).

use std::path::Path;

use nalgebra::Vector3;
use serde::Serialize;
use sim::score::{self, Detected, Score};
use sim::truth_file::{At, ScoreInputError, TruthFile, TruthReadError, score_detections};

use crate::replay::LogReplay;

/// A fulcrum farther than this from the true trocar (metres) is a wrong-trocar detection.
pub const WRONG_TROCAR_M: f64 = 0.03;

/// Why a replay could not be scored.
#[derive(Debug, thiserror::Error)]
pub enum ScoreError {
    /// The truth file could not be read.
    #[error(transparent)]
    Truth(#[from] TruthReadError),
    /// The replay does not line up with the truth file.
    #[error(transparent)]
    Input(#[from] ScoreInputError),
}

/// A score with its figures in a printable and serialisable form.
#[derive(Clone, Debug, Serialize)]
pub struct ScoreReport {
    /// True insertions.
    pub insertions: usize,
    /// Insertions detected.
    pub insertions_detected: usize,
    /// Mean insertion delay, seconds.
    pub insertion_delay_mean_s: f64,
    /// Median insertion delay, seconds.
    pub insertion_delay_p50_s: f64,
    /// 95th percentile insertion delay, seconds.
    pub insertion_delay_p95_s: f64,
    /// True extractions.
    pub extractions: usize,
    /// Extractions detected.
    pub extractions_detected: usize,
    /// Mean extraction delay, seconds.
    pub extraction_delay_mean_s: f64,
    /// Median extraction delay, seconds.
    pub extraction_delay_p50_s: f64,
    /// 95th percentile extraction delay, seconds.
    pub extraction_delay_p95_s: f64,
    /// False detections (outside, or at the wrong trocar).
    pub false_detections: usize,
    /// Mean localisation error at first detection, metres.
    pub first_error_mean_m: f64,
    /// Root-mean-square localisation error while inside, metres.
    pub rms_error_m: f64,
}

impl ScoreReport {
    /// Figures of a [`Score`].
    pub fn from_score(s: &Score) -> Self {
        Self {
            insertions: s.insertions,
            insertions_detected: s.insertions_detected,
            insertion_delay_mean_s: score::mean(&s.insertion_delays_s),
            insertion_delay_p50_s: score::quantile(&s.insertion_delays_s, 0.5),
            insertion_delay_p95_s: score::quantile(&s.insertion_delays_s, 0.95),
            extractions: s.extractions,
            extractions_detected: s.extractions_detected,
            extraction_delay_mean_s: score::mean(&s.extraction_delays_s),
            extraction_delay_p50_s: score::quantile(&s.extraction_delays_s, 0.5),
            extraction_delay_p95_s: score::quantile(&s.extraction_delays_s, 0.95),
            false_detections: s.false_detections,
            first_error_mean_m: score::mean(&s.first_errors_m),
            rms_error_m: s.rms_error_m,
        }
    }

    /// One paragraph for people.
    pub fn describe(&self) -> String {
        format!(
            "insertions {}/{} detected, delay mean {:.3} s (p50 {:.3}, p95 {:.3}); \
             extractions {}/{} detected, delay mean {:.3} s (p50 {:.3}, p95 {:.3}); \
             false detections {}; first-detection error {:.1} mm; RMS error {:.2} mm",
            self.insertions_detected,
            self.insertions,
            self.insertion_delay_mean_s,
            self.insertion_delay_p50_s,
            self.insertion_delay_p95_s,
            self.extractions_detected,
            self.extractions,
            self.extraction_delay_mean_s,
            self.extraction_delay_p50_s,
            self.extraction_delay_p95_s,
            self.false_detections,
            self.first_error_mean_m * 1e3,
            self.rms_error_m * 1e3
        )
    }
}

/// Scores the cycles of a candump replay against a truth file (cycles are matched to truth
/// samples by their SYNC timestamps). An invalid cycle counts as "not inside".
pub fn score_log(log: &LogReplay, truth_path: &Path) -> Result<ScoreReport, ScoreError> {
    let truth = TruthFile::open(truth_path)?;
    let detections = log.cycles.iter().map(|c| {
        let inside = c.output.state.is_inside();
        let f = c.output.fulcrum_base_m;
        (
            At::UnixTimeUs(c.sync_unix_us),
            Detected { inside, fulcrum_base_m: inside.then(|| Vector3::new(f[0], f[1], f[2])) },
        )
    });
    let s = score_detections(&truth, detections, WRONG_TROCAR_M)?;
    Ok(ScoreReport::from_score(&s))
}
