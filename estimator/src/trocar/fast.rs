//! comanip's fast trocar detector.
//!
//! The paper decides on fixed windows of 20 and 100 lines, each line included only after
//! 5 mm or 5° of motion, and re-solves the least squares over the whole window. Its delays
//! come from waiting for those windows to fill with lines of the new situation. This
//! detector decides instead on the *longest recent segment of lines that is consistent with
//! one point*, and on each 1 ms sample as it arrives:
//!
//! 1. **Inclusion** as in the paper's Algorithm 1, with finer thresholds (1 mm / 0.5°):
//!    more, closer lines, so a trocar is seen after a smaller sweep.
//! 2. **O(1) sliding normal equations** ([`super::lsq::NormalSums`]): adding or removing a
//!    line costs a few flops, the fit is a 3×3 symmetric eigen-solve, and the sum of squared
//!    residuals comes from the sums. A periodic rebuild from the window bounds drift.
//! 3. **Segmentation**: a new line far (`break_gate_m`) from a well-determined segment
//!    fulcrum starts a new segment; a segment whose RMS residual exceeds
//!    `consistency_rms_m` loses its oldest lines until it is consistent. So lines from
//!    before an insertion leave the fit quickly instead of after `m` new lines.
//! 4. **Conditioning gate and covariance**: the fulcrum's one-sigma uncertainty
//!    `σ / sqrt(λ_min(Σ(I − z zᵀ)))`, with σ the residual-based noise estimate floored at
//!    `noise_floor_m`, must be below `insert_max_std_m`: nearly parallel lines never make a
//!    trocar, however small their residual.
//! 5. **Signed depth guard**: the fulcrum must lie in front of the wrist, towards the tip,
//!    by `insert_min_depth_m` (the paper's guard is unsigned).
//! 6. **Persistence**: the consistent segment must span `min_persistence_s`.
//! 7. **Per-sample innovation for extraction**: while inside, every sample's line distance
//!    to the fulcrum is tested; `extract_persistence_s` of uninterrupted evidence above
//!    `extract_gate_m` ends the insertion.
//! 8. **Instrument length (optional)**: the tip is at `P + L·z`; insertion needs it beyond
//!    the fulcrum and extraction is declared as soon as it comes back over the fulcrum,
//!    with no need for lateral motion.
//! 9. **Trocar memory (optional)**: trocars found earlier are remembered; a line that keeps
//!    passing through one of them (with the tip beyond it when the length is known, or while
//!    the axis pivots about it when it is not) is a re-insertion after a few tens of ms.

use heapless::{Deque, Vec};
use nalgebra::Vector3;

use super::config::{ConfigError, FastConfig};
use super::lsq::{self, LsFit, NormalSums};

#[inline]
fn libm_sqrt(x: f64) -> f64 {
    nalgebra::ComplexField::sqrt(x)
}
use super::{Estimate, FitSummary, LineSample, MEMORY_CAPACITY, TrocarState, WINDOW_CAPACITY, differs_enough};

/// Numerical guard on `λ_min/q` for the solve itself (the real gate is `insert_max_std_m`).
const MIN_CONDITIONING: f64 = 1e-9;
/// Most lines trimmed from a segment per sample (bounds the step's worst case).
const MAX_TRIMS_PER_STEP: usize = 2;
/// Fewest lines a trimmed segment keeps.
const MIN_SEGMENT_AFTER_TRIM: usize = 3;
/// Samples of uninterrupted tip-over-fulcrum evidence before extraction (debounce).
const TIP_DEBOUNCE_SAMPLES: u32 = 3;
/// Weight of one sample in the running mean square distance of the lines to the fulcrum
/// while inside (about 2 s of memory at 1 kHz).
const INNOVATION_ALPHA: f64 = 1.0 / 2000.0;
/// Axis rotation (radians) a memory re-insertion needs when the instrument length is unknown.
const MEMORY_MIN_SWEEP_RAD: f64 = 0.02;

#[derive(Clone, Copy, Debug)]
struct Stored {
    line: LineSample,
    step: u64,
}

#[derive(Clone, Copy, Debug)]
struct KnownTrocar {
    id: u8,
    fulcrum_base_m: Vector3<f64>,
    last_seen_step: u64,
    /// Confirmed insertions merged into this entry (capped: the entry follows a trocar
    /// that moves slowly, e.g. when the patient is repositioned).
    visits: u32,
}

/// A line passes *through* the fulcrum, for the slide evidence, when it is within this many
/// times the segment's RMS line distance of it ...
const SLIDE_THROUGH_SIGMAS: f64 = 2.0;
/// ... or within this distance, metres (quantisation floor).
const SLIDE_THROUGH_MIN_M: f64 = 0.00025;

/// The slide evidence ignores `1/SLIDE_TRIM_DIVISOR` of the lines at each end of the depth
/// range (its 10th to 90th percentiles).
const SLIDE_TRIM_DIVISOR: usize = 10;

/// Newest lines of the segment that must still pass through the fulcrum for an insertion ...
const RECENT_LINES: usize = 3;
/// ... within this many times the segment's RMS line distance.
const RECENT_SIGMAS: f64 = 3.0;

/// Most visits an entry's fulcrum averages over.
const MEMORY_MAX_VISITS: u32 = 8;

#[derive(Clone, Copy, Debug)]
struct MemoryCandidate {
    slot: usize,
    samples: u32,
    first_axis: Vector3<f64>,
    swept: bool,
}

/// comanip's detector. Construct with [`FastDetector::new`]; call [`FastDetector::step`] once
/// per sample.
#[derive(Clone, Debug)]
pub struct FastDetector {
    cfg: FastConfig,
    cos_include: f64,
    min_persistence_steps: u64,
    extract_persistence_steps: u32,
    memory_persistence_steps: u32,
    confirm_steps: u64,
    segment: Deque<Stored, WINDOW_CAPACITY>,
    sums: NormalSums,
    updates_since_rebuild: u32,
    fit: Option<LsFit>,
    last_included: Option<LineSample>,
    step_index: u64,
    state: TrocarState,
    fulcrum_base_m: Vector3<f64>,
    out_count: u32,
    tip_count: u32,
    inside_sums: NormalSums,
    innovation_ms_m2: f64,
    memory: Vec<KnownTrocar, MEMORY_CAPACITY>,
    next_id: u8,
    candidate: Option<MemoryCandidate>,
    /// Step of the current insertion.
    inside_since_step: u64,
    /// The current insertion is a confirmed trocar (lasted `confirm_s`, or re-entered from
    /// the list).
    confirmed: bool,
    last: Estimate,
    /// The next sample follows a gap in the input: check it against the state at once.
    after_gap: bool,
}

fn steps(seconds: f64, period_s: f64) -> u64 {
    // Validated: both finite, period > 0, seconds in [0, 10].
    let n = seconds / period_s;
    if n <= 0.0 { 0 } else { nalgebra::ComplexField::ceil(n - 1e-9) as u64 }
}

impl FastDetector {
    /// Builds the detector (validates `cfg`); `sample_period_s` converts durations to samples.
    pub fn new(cfg: &FastConfig, sample_period_s: f64) -> Result<Self, ConfigError> {
        cfg.validate()?;
        if !(sample_period_s.is_finite() && sample_period_s > 0.0 && sample_period_s <= 1.0) {
            return Err(ConfigError::OutOfRange {
                key: "sample_period_s",
                value: sample_period_s,
                allowed: "(0, 1] s",
            });
        }
        Ok(Self {
            cfg: *cfg,
            cos_include: nalgebra::ComplexField::cos(cfg.include_angle_deg.to_radians()),
            min_persistence_steps: steps(cfg.min_persistence_s, sample_period_s),
            extract_persistence_steps: steps(cfg.extract_persistence_s, sample_period_s).max(1) as u32,
            memory_persistence_steps: steps(cfg.memory_persistence_s, sample_period_s).max(1) as u32,
            confirm_steps: steps(cfg.confirm_s, sample_period_s),
            segment: Deque::new(),
            sums: NormalSums::new(),
            updates_since_rebuild: 0,
            fit: None,
            last_included: None,
            step_index: 0,
            state: TrocarState::Outside,
            fulcrum_base_m: Vector3::zeros(),
            out_count: 0,
            tip_count: 0,
            inside_sums: NormalSums::new(),
            innovation_ms_m2: 0.0,
            memory: Vec::new(),
            next_id: 0,
            candidate: None,
            inside_since_step: 0,
            confirmed: false,
            last: Estimate::outside(),
            after_gap: false,
        })
    }

    /// Forgets every line and returns to `Outside`; keeps the trocar memory.
    pub fn reset(&mut self) {
        self.segment.clear();
        self.sums = NormalSums::new();
        self.fit = None;
        self.last_included = None;
        self.state = TrocarState::Outside;
        self.out_count = 0;
        self.tip_count = 0;
        self.candidate = None;
        self.confirmed = false;
        self.after_gap = false;
        self.last = Estimate::outside();
    }

    /// A short gap in the input ended: the next sample is checked against the state at once
    /// (inside: extraction without persistence if the line has left the fulcrum or the tip
    /// is back over it; outside: nothing to check, the segment goes on).
    pub fn check_after_gap(&mut self) {
        self.after_gap = true;
    }

    /// The check of the first sample after a gap (see [`Self::check_after_gap`]). Returns
    /// true when the insertion ended.
    fn resume_check(&mut self, line: &LineSample) -> bool {
        self.after_gap = false;
        self.candidate = None;
        if !self.state.is_inside() {
            // Outside, the segment goes on: in at most `max_gap_s` (50 ms) the hand moves a
            // few millimetres, and the lines before and after the gap are one motion. (An
            // earlier version restarted the segment here: at 1 % TPDO loss no segment ever
            // lasted the persistence time, and no insertion was detected.)
            return false;
        }
        let off = lsq::line_distance(line, &self.fulcrum_base_m) > self.extract_gate_m();
        let tip_out = self
            .cfg
            .instrument_length_m
            .is_some_and(|l| lsq::signed_depth(line, &self.fulcrum_base_m) > l + self.cfg.tip_margin_m);
        if off || tip_out {
            self.leave(line);
            return true;
        }
        self.out_count = 0;
        self.tip_count = 0;
        false
    }

    /// The trocar list: confirmed trocars as `(id, fulcrum)` pairs, metres, robot base frame.
    /// An insertion enters it once it has lasted `confirm_s` (merged with an entry within
    /// `memory_merge_m`, whose fulcrum becomes the mean of its visits); the entry seen least
    /// recently is forgotten when the list is full.
    pub fn known_trocars(&self) -> impl Iterator<Item = (u8, Vector3<f64>)> + '_ {
        self.memory.iter().map(|k| (k.id, k.fulcrum_base_m))
    }

    fn noise_m(&self, fit: &LsFit) -> f64 {
        fit.noise_estimate_m().max(self.cfg.noise_floor_m)
    }

    fn fulcrum_std_m(&self, fit: &LsFit) -> f64 {
        fit.fulcrum_std_m(self.noise_m(fit))
    }

    fn well_determined(&self, fit: &LsFit) -> bool {
        self.fulcrum_std_m(fit) <= self.cfg.insert_max_std_m
    }

    fn refit(&mut self) {
        self.fit = self.sums.solve(MIN_CONDITIONING).ok();
    }

    fn restart_segment(&mut self, line: &LineSample) {
        self.segment.clear();
        self.sums = NormalSums::new();
        self.updates_since_rebuild = 0;
        let _ = self.segment.push_back(Stored { line: *line, step: self.step_index });
        self.sums.add(line);
        self.fit = None;
    }

    fn pop_oldest(&mut self) {
        if let Some(old) = self.segment.pop_front() {
            self.sums.remove(&old.line);
            self.updates_since_rebuild += 1;
        }
    }

    /// Segment maintenance for an included line (steps 2-3 of the module doc).
    fn include(&mut self, line: &LineSample) {
        if let Some(fit) = self.fit
            && self.well_determined(&fit)
            && lsq::line_distance(line, &fit.fulcrum_base_m) > self.cfg.break_gate_m
        {
            if self.state.is_inside() {
                // Inside, an outlier does not enter the fit; the per-sample test decides
                // whether the instrument has left.
                return;
            }
            self.restart_segment(line);
            return;
        }
        while self.segment.len() >= self.cfg.window {
            self.pop_oldest();
        }
        let _ = self.segment.push_back(Stored { line: *line, step: self.step_index });
        self.sums.add(line);
        self.updates_since_rebuild += 1;
        if self.updates_since_rebuild >= self.cfg.rebuild_every {
            self.sums.rebuild(self.segment.iter().map(|s| &s.line));
            self.updates_since_rebuild = 0;
        }
        self.refit();
        let mut trims = 0;
        while trims < MAX_TRIMS_PER_STEP && self.segment.len() > MIN_SEGMENT_AFTER_TRIM {
            match self.fit {
                Some(f) if f.rms_m > self.cfg.consistency_rms_m => {
                    self.pop_oldest();
                    self.refit();
                    trims += 1;
                }
                _ => break,
            }
        }
    }

    fn fresh_id(&mut self) -> u8 {
        let id = self.next_id;
        self.next_id = self.next_id.wrapping_add(1);
        id
    }

    fn memory_slot_near(&self, point: &Vector3<f64>, within_m: f64) -> Option<usize> {
        let mut best: Option<(usize, f64)> = None;
        for (i, k) in self.memory.iter().enumerate() {
            let d = (k.fulcrum_base_m - point).norm();
            if d < within_m && best.is_none_or(|(_, bd)| d < bd) {
                best = Some((i, d));
            }
        }
        best.map(|(i, _)| i)
    }

    /// Records `fulcrum` in the memory (merging with a known trocar); returns its id.
    fn remember(&mut self, fulcrum: &Vector3<f64>) -> u8 {
        let now = self.step_index;
        if let Some(i) = self.memory_slot_near(fulcrum, self.cfg.memory_merge_m) {
            let k = &mut self.memory[i];
            let n = f64::from(k.visits);
            k.fulcrum_base_m = (k.fulcrum_base_m * n + fulcrum) / (n + 1.0);
            k.visits = (k.visits + 1).min(MEMORY_MAX_VISITS);
            k.last_seen_step = now;
            return k.id;
        }
        let id = match self.state {
            // A provisional id of this insertion that matches no entry becomes the entry's.
            TrocarState::Inside { id } if !self.memory.iter().any(|k| k.id == id) => id,
            _ => self.fresh_id(),
        };
        let entry = KnownTrocar { id, fulcrum_base_m: *fulcrum, last_seen_step: now, visits: 1 };
        if self.memory.push(entry).is_err() {
            // Full: replace the trocar seen least recently.
            let mut oldest = 0;
            for (i, k) in self.memory.iter().enumerate() {
                if k.last_seen_step < self.memory[oldest].last_seen_step {
                    oldest = i;
                }
            }
            self.memory[oldest] = entry;
        }
        id
    }

    fn tip_beyond(&self, depth_m: f64) -> bool {
        match self.cfg.instrument_length_m {
            Some(l) => depth_m < l - self.cfg.tip_margin_m,
            None => true,
        }
    }

    fn enter(&mut self, fulcrum: Vector3<f64>, id: u8, confirmed: bool) {
        self.state = TrocarState::Inside { id };
        self.inside_since_step = self.step_index;
        self.confirmed = confirmed;
        self.fulcrum_base_m = fulcrum;
        self.inside_sums = self.sums;
        let g0 = self.cfg.extract_gate_m / self.cfg.extract_gate_sigmas;
        self.innovation_ms_m2 = g0 * g0;
        self.out_count = 0;
        self.tip_count = 0;
        self.candidate = None;
    }

    /// Ends the insertion: a confirmed one enters (or updates) the trocar list.
    fn end_insertion(&mut self) {
        if self.confirmed {
            let f = self.fulcrum_base_m;
            self.remember(&f);
        }
        self.confirmed = false;
    }

    fn leave(&mut self, line: &LineSample) {
        self.end_insertion();
        self.state = TrocarState::Outside;
        self.out_count = 0;
        self.tip_count = 0;
        self.candidate = None;
        self.restart_segment(line);
        self.last_included = Some(*line);
    }

    /// The adaptive extraction gate, metres (step 7).
    fn extract_gate_m(&self) -> f64 {
        (self.cfg.extract_gate_sigmas * libm_sqrt(self.innovation_ms_m2))
            .clamp(self.cfg.extract_gate_min_m, self.cfg.extract_gate_m)
    }

    /// Extraction tests on every sample (steps 7-8).
    fn check_extraction(&mut self, line: &LineSample) -> bool {
        let d = lsq::line_distance(line, &self.fulcrum_base_m);
        let gate = self.extract_gate_m();
        if d > gate {
            self.out_count += 1;
        } else {
            self.out_count = 0;
            self.innovation_ms_m2 += INNOVATION_ALPHA * (d * d - self.innovation_ms_m2);
        }
        if let Some(l) = self.cfg.instrument_length_m {
            let s = lsq::signed_depth(line, &self.fulcrum_base_m);
            self.tip_count = if s > l + self.cfg.tip_margin_m { self.tip_count + 1 } else { 0 };
        }
        self.out_count >= self.extract_persistence_steps || self.tip_count >= TIP_DEBOUNCE_SAMPLES
    }

    /// Re-insertion into a remembered trocar (step 9).
    fn check_memory(&mut self, line: &LineSample) -> Option<(Vector3<f64>, u8)> {
        let mut supported: Option<usize> = None;
        for (i, k) in self.memory.iter().enumerate() {
            let d = lsq::line_distance(line, &k.fulcrum_base_m);
            let s = lsq::signed_depth(line, &k.fulcrum_base_m);
            if d < self.cfg.memory_gate_m && s > self.cfg.insert_min_depth_m && self.tip_beyond(s) {
                supported = Some(i);
                break;
            }
        }
        let Some(slot) = supported else {
            self.candidate = None;
            return None;
        };
        let c = match self.candidate {
            Some(c) if c.slot == slot => c,
            _ => MemoryCandidate { slot, samples: 0, first_axis: line.axis_base, swept: false },
        };
        let swept = c.swept || c.first_axis.dot(&line.axis_base) < nalgebra::ComplexField::cos(MEMORY_MIN_SWEEP_RAD);
        let c = MemoryCandidate { samples: c.samples + 1, swept, ..c };
        self.candidate = Some(c);
        let evidence = self.cfg.instrument_length_m.is_some() || c.swept;
        if c.samples >= self.memory_persistence_steps && evidence {
            let k = self.memory[slot];
            return Some((k.fulcrum_base_m, k.id));
        }
        None
    }

    /// Insertion test on the current segment fit (steps 4-6).
    fn check_insertion(&self, line: &LineSample) -> Option<Vector3<f64>> {
        let fit = self.fit?;
        let first = self.segment.front()?;
        let f = fit.fulcrum_base_m;
        let depth = lsq::signed_depth(line, &f);
        let cross = self.cfg.insert_min_cross_spread_deg.to_radians();
        let ok = self.segment.len() >= self.cfg.min_lines
            && self.well_determined(&fit)
            && fit.minor_spread_rad2 >= cross * cross
            && fit.rms_m <= self.cfg.consistency_rms_m
            && depth > self.cfg.insert_min_depth_m
            && self.tip_beyond(depth)
            && self.step_index - first.step >= self.min_persistence_steps
            && lsq::line_distance(line, &f) <= self.cfg.extract_gate_m
            && self.newest_consistent(&f, fit.rms_m)
            && self.slide_range_m(&f, (SLIDE_THROUGH_SIGMAS * fit.rms_m).max(SLIDE_THROUGH_MIN_M))
                >= self.cfg.insert_min_slide_m;
        ok.then_some(f)
    }

    /// How far the instrument has slid through `point` over the newer half of the segment's
    /// lines, metres: the spread of `zᵀ(point − P)` between its 10th and 90th percentiles,
    /// over the lines
    /// that pass through the point within `through_m`. Lines at the ends of a virtual pivot
    /// (where the hand starts to move away, or the few lines of a slide before the pivot
    /// began) are not a slide *through* the point while it pivots: the distance gate drops
    /// the first, the percentiles the second. Allocation-free (a stack buffer and two
    /// selections, O(window)); evaluated last, only when every other insertion test has
    /// passed.
    fn slide_range_m(&self, point: &Vector3<f64>, through_m: f64) -> f64 {
        let mut depths = [0.0_f64; WINDOW_CAPACITY];
        let mut n = 0;
        // The newer half of the segment: a trocar lets the tool slide through it while it
        // pivots, now; a slide followed by a pivot (a hovering hand) slides only in the
        // older half.
        let skip = self.segment.len() / 2;
        for s in self.segment.iter().skip(skip) {
            if lsq::line_distance(&s.line, point) <= through_m && n < WINDOW_CAPACITY {
                depths[n] = lsq::signed_depth(&s.line, point);
                n += 1;
            }
        }
        if n < 2 {
            return 0.0;
        }
        let d = &mut depths[..n];
        let k = n / SLIDE_TRIM_DIVISOR;
        let (_, lo, _) = d.select_nth_unstable_by(k, f64::total_cmp);
        let lo = *lo;
        let (_, hi, _) = d.select_nth_unstable_by(n - 1 - k, f64::total_cmp);
        *hi - lo
    }

    /// Do the newest lines of the segment still pass through `point`, within
    /// `RECENT_SIGMAS` times the segment's RMS distance `rms_m`? A trocar keeps the current
    /// line on the fulcrum; at the end of a virtual pivot the newest lines drift away from
    /// it, one after the other, while the old ones keep the RMS low.
    fn newest_consistent(&self, point: &Vector3<f64>, rms_m: f64) -> bool {
        let gate = RECENT_SIGMAS * rms_m.max(SLIDE_THROUGH_MIN_M);
        self.segment.iter().rev().take(RECENT_LINES).all(|s| lsq::line_distance(&s.line, point) <= gate)
    }

    /// The trocar id for an insertion at `fulcrum`: the listed trocar within twice the merge
    /// distance (a first detection is less precise than a listed fulcrum), else a new
    /// provisional id.
    fn id_for(&mut self, fulcrum: &Vector3<f64>) -> (u8, bool) {
        match self.memory_slot_near(fulcrum, 2.0 * self.cfg.memory_merge_m) {
            Some(i) => (self.memory[i].id, true),
            None => (self.fresh_id(), false),
        }
    }

    /// Feeds one sample; returns the estimate after it. Allocation-free; O(1) except for the
    /// periodic rebuild (O(window) once every `rebuild_every` updates).
    pub fn step(&mut self, sample: &LineSample) -> Estimate {
        let line = match sample.validated() {
            Ok(l) => l,
            Err(e) => return Estimate { rejected: Some(e), included: false, ..self.last },
        };
        self.step_index += 1;

        if self.after_gap && self.resume_check(&line) {
            // Left during the gap: reported outside from this sample on.
        } else if self.state.is_inside() {
            if self.check_extraction(&line) {
                self.leave(&line);
            }
        } else if self.cfg.trocar_memory
            && !self.memory.is_empty()
            && let Some((f, id)) = self.check_memory(&line)
        {
            self.enter(f, id, true);
            self.restart_segment(&line);
            self.last_included = Some(line);
        }

        let included = match &self.last_included {
            None => true,
            Some(last) => differs_enough(last, &line, self.cfg.include_distance_m, self.cos_include),
        };
        if !included
            && !self.state.is_inside()
            && let Some(last) = &self.last_included
            && nalgebra::ComplexField::abs(lsq::signed_depth(last, &line.wrist_base_m)) > self.cfg.slide_restart_m
        {
            // A pure slide along the axis (step 3b): the lines before it were the approach.
            self.restart_segment(&line);
            self.last_included = Some(line);
        }
        if included {
            self.last_included = Some(line);
            self.include(&line);
        }

        match self.state {
            TrocarState::Outside => {
                if let Some(f) = self.check_insertion(&line) {
                    let (id, listed) = self.id_for(&f);
                    self.enter(f, id, listed);
                }
            }
            TrocarState::Inside { .. } => {
                if !self.confirmed && self.step_index - self.inside_since_step >= self.confirm_steps {
                    self.confirmed = true;
                }

                if included && lsq::line_distance(&line, &self.fulcrum_base_m) <= self.extract_gate_m() {
                    self.inside_sums.decay(1.0 - 1.0 / self.cfg.inside_memory_lines);
                    self.inside_sums.add(&line);
                    if let Ok(fit) = self.inside_sums.solve(MIN_CONDITIONING)
                        && self.well_determined(&fit)
                    {
                        self.fulcrum_base_m = fit.fulcrum_base_m;
                    }
                }
            }
        }

        let est = Estimate {
            state: self.state,
            fulcrum_base_m: self.state.is_inside().then_some(self.fulcrum_base_m),
            fit: self.fit.map(|f| FitSummary {
                point_base_m: f.fulcrum_base_m,
                residual_m: f.rms_m,
                conditioning: f.conditioning,
                std_m: self.fulcrum_std_m(&f),
                lines: f.count as u16,
                minor_spread_rad2: f.minor_spread_rad2,
            }),
            window_fill: self.segment.len() as u16,
            window_len: self.cfg.window as u16,
            rejected: None,
            included,
        };
        self.last = est;
        est
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{UnitQuaternion, Vector3};
    use std::vec::Vec;

    use crate::trocar::test_support::{Phase, cone_axis, cone_swing, detector, ever_inside, line_through, scripted};
    use crate::trocar::{Detector, DetectorConfig, DetectorMode, FastConfig, LineSample};

    #[test]
    fn nearly_parallel_lines_through_a_point_do_not_make_a_trocar_in_fast_mode() {
        // Lines that do pass through one point but span only 0.3 degrees: the residual is tiny,
        // yet the point is undetermined along the axis. The conditioning gate must refuse it.
        let f = Vector3::new(0.4, 0.0, 0.0);
        let mut d = detector(DetectorMode::Fast);
        for k in 0..20_000 {
            let t = k as f64 * 0.001;
            let axis = cone_axis(0.1 + 0.0026 * (2.0 * t).sin(), 1.0);
            // Move the wrist along the axis too so lines keep being included.
            let e = d.step(&line_through(&f, &axis, 0.2 + 0.05 * (1.5 * t).sin()));
            assert!(!e.state.is_inside(), "fast mode declared an undetermined trocar at {t} s");
        }
    }

    /// Lines through `f` whose axes swing about one fixed axis only (a coplanar pencil): every
    /// one-parameter motion has such a virtual pivot, so the fast mode must not call it a trocar;
    /// the same point approached from a cone of directions is one.
    #[test]
    fn a_one_axis_swing_is_not_a_trocar_but_a_cone_through_the_same_point_is() {
        let f = Vector3::new(0.32, -0.02, 0.0);
        let run = |cone: bool| {
            let mut d = detector(DetectorMode::Fast);
            let mut inside = false;
            for i in 0..3000 {
                let t = i as f64 * 1e-3;
                let pitch = 0.2 * (2.0 * core::f64::consts::PI * 0.4 * t).sin();
                let yaw = if cone { 0.15 * (2.0 * core::f64::consts::PI * 0.3 * t).sin() } else { 0.0 };
                let axis =
                    (UnitQuaternion::from_euler_angles(pitch, yaw, 0.0) * Vector3::new(0.0, 0.0, -1.0)).normalize();
                // The instrument slides through the point (±1 cm), as through a body wall.
                let depth = 0.20 + 0.01 * (2.0 * core::f64::consts::PI * 0.25 * t).sin();
                let e = d.step(&line_through(&f, &axis, depth));
                inside |= e.state.is_inside();
            }
            inside
        };
        assert!(!run(false), "a coplanar pencil of lines was taken for a trocar");
        assert!(run(true), "lines through one point from a cone of directions were not detected");
    }

    /// Outside, sliding the instrument along its own axis (entering a port) starts a new segment:
    /// the lines of the approach before it no longer take part in the fit.
    #[test]
    fn an_axial_slide_restarts_the_segment_outside() {
        let mut d = detector(DetectorMode::Fast);
        // A wandering free motion: lines through no common point.
        for i in 0..400 {
            let t = i as f64 * 1e-3;
            let axis = cone_axis(0.3 + 0.2 * t, 2.0 * t);
            let wrist = Vector3::new(0.3 + 0.1 * t, 0.05 * t, 0.3);
            d.step(&LineSample::new(wrist, axis));
        }
        let axis = cone_axis(0.38, 0.8);
        let start = Vector3::new(0.34, 0.02, 0.3);
        let before = d.step(&LineSample::new(start, axis));
        assert!(before.window_fill > 1, "the free motion should have built a segment");
        // Slide 3 cm along the axis, 0.1 mm per sample: no lateral motion, no rotation.
        let mut e = before;
        for k in 1..=300 {
            e = d.step(&LineSample::new(start + axis * (k as f64 * 1e-4), axis));
        }
        assert_eq!(e.window_fill, 1, "the slide should have restarted the segment");
        assert!(!e.state.is_inside());
    }

    /// Inside a trocar whose lines are quiet, the extraction gate adapts down from
    /// `extract_gate_m` (8 mm) towards `extract_gate_min_m`: a line 4 mm off the fulcrum ends
    /// the insertion, where the fixed 8 mm gate would not.
    #[test]
    fn the_adaptive_extraction_gate_sees_a_small_departure() {
        let f = Vector3::new(0.3, 0.0, 0.0);
        let run = |adaptive: bool| {
            let mut cfg = DetectorConfig { mode: DetectorMode::Fast, ..Default::default() };
            if !adaptive {
                cfg.fast.extract_gate_min_m = cfg.fast.extract_gate_m;
            }
            let mut d = Detector::new(&cfg).unwrap();
            let mut inside_at = None;
            for i in 0..8000 {
                let t = i as f64 * 1e-3;
                let axis = cone_axis(0.2 + 0.1 * (1.3 * t).sin(), 1.7 * t);
                // From 7 s on, the line passes 4 mm beside the fulcrum (the instrument has left).
                let offset = if t >= 7.0 { axis.cross(&Vector3::x()).normalize() * 0.004 } else { Vector3::zeros() };
                // The instrument slides in and out of the trocar (±1 cm), as in any manipulation.
                let depth = 0.2 + 0.01 * (0.9 * t).sin();
                let e = d.step(&line_through(&(f + offset), &axis, depth));
                if t < 7.0 && e.state.is_inside() && inside_at.is_none() {
                    inside_at = Some(t);
                }
                if t >= 7.0 && !e.state.is_inside() {
                    return (inside_at, Some(t - 7.0));
                }
            }
            (inside_at, None)
        };
        let (inside, out) = run(true);
        assert!(inside.is_some(), "the trocar was not detected");
        let out = out.expect("the adaptive gate did not see the 4 mm departure");
        assert!(out < 0.05, "extraction took {out} s");
        let (_, fixed) = run(false);
        assert!(fixed.is_none(), "the fixed 8 mm gate should not see a 4 mm departure");
    }

    fn fast(cfg: FastConfig) -> Detector {
        Detector::new(&DetectorConfig { mode: DetectorMode::Fast, fast: cfg, ..Default::default() }).unwrap()
    }

    #[test]
    fn a_hand_pivot_about_a_point_of_the_shaft_is_not_a_trocar_but_a_slide_through_it_is() {
        let f = Vector3::new(0.30, -0.02, 0.05);
        // The hand swings the instrument about a point 12 cm in front of the wrist, for 3 s:
        // consistent lines, a cone of directions, 12 cm deep, persistent, and no slide.
        let pivot = cone_swing(&f, 3.0, |_| 0.12);
        assert!(
            !ever_inside(&mut fast(FastConfig::default()), &pivot),
            "a virtual pivot of the hand was taken for a trocar"
        );
        // Without the slide evidence, the same motion is declared (the test is not vacuous).
        let no_slide = FastConfig { insert_min_slide_m: 0.0, ..Default::default() };
        assert!(ever_inside(&mut fast(no_slide), &pivot), "the motion should pass every other insertion test");
        // The same swing while the instrument slides in and out of the point (±1 cm at 0.3 Hz).
        let trocar = cone_swing(&f, 3.0, |t| 0.12 + 0.01 * (2.0 * core::f64::consts::PI * 0.3 * t).sin());
        assert!(
            ever_inside(&mut fast(FastConfig::default()), &trocar),
            "a trocar with sliding motion was not detected"
        );
    }

    #[test]
    fn a_slide_before_the_pivot_is_not_a_slide_through_it() {
        // A hovering approach: the instrument slides 8 mm along its axis (less than the
        // segment-restart slide), then the hand pivots about the tip without sliding.
        let f = Vector3::new(0.30, 0.02, 0.04);
        let axis = Vector3::new(0.0, 0.0, -1.0);
        let mut d = fast(FastConfig::default());
        let mut inside = false;
        for i in 0..400 {
            // Tiny lateral jitter so that a few approach lines are included.
            let jitter = Vector3::new(0.0015 * ((i / 100) % 2) as f64, 0.0, 0.0);
            let l = line_through(&(f + jitter), &axis, 0.30 - 0.008 * i as f64 / 400.0);
            inside |= d.step(&l).state.is_inside();
        }
        inside |= ever_inside(&mut d, &cone_swing(&f, 3.0, |_| 0.30));
        assert!(!inside, "a pivot about the tip after a short slide was taken for a trocar");
    }

    #[test]
    fn only_confirmed_insertions_enter_the_trocar_list_and_visits_merge() {
        let t1 = Vector3::new(0.30, -0.05, 0.02);
        let t2 = Vector3::new(0.32, 0.06, 0.01);
        let sliding = |f: &Vector3<f64>, s: f64| {
            cone_swing(f, s, |t| 0.15 + 0.01 * (2.0 * core::f64::consts::PI * 0.3 * t).sin())
        };
        let cfg = FastConfig { confirm_s: 1.5, ..Default::default() };
        let mut d = fast(cfg);
        // A short insertion at t1 (detected, left after well under 1.5 s): not listed.
        let short = sliding(&t1, 1.2);
        assert!(ever_inside(&mut d, &short));
        // Leave by moving far away laterally (a jump the extraction test sees at once).
        let away = LineSample::new(Vector3::new(0.0, 0.0, 0.6), Vector3::new(1.0, 0.0, 0.0));
        for _ in 0..50 {
            d.step(&away);
        }
        assert!(!d.step(&away).state.is_inside());
        assert!(d.known_trocars().is_empty(), "an unconfirmed insertion entered the list: {:?}", d.known_trocars());
        // A long insertion at t2: listed at its extraction.
        assert!(ever_inside(&mut d, &sliding(&t2, 4.0)));
        for _ in 0..50 {
            d.step(&away);
        }
        let list = d.known_trocars();
        assert_eq!(list.len(), 1, "{list:?}");
        assert!((list[0].1 - t2).norm() < 2e-3, "listed fulcrum off: {}", list[0].1);
        let id2 = list[0].0;
        // A second long visit of t2 merges into the same entry and reports the same id.
        let mut ids = Vec::new();
        for l in sliding(&t2, 4.0) {
            if let crate::trocar::TrocarState::Inside { id } = d.step(&l).state {
                ids.push(id);
            }
        }
        assert!(!ids.is_empty() && ids.iter().all(|&id| id == id2), "second visit ids {ids:?}, expected {id2}");
        for _ in 0..50 {
            d.step(&away);
        }
        assert_eq!(d.known_trocars().len(), 1, "a second visit made a second entry");
    }

    /// After a short gap in the input the first fresh line is checked at once: still through
    /// the fulcrum, the trocar is kept; off it (the instrument left during the gap), the
    /// insertion ends on that very sample, without the usual persistence. A gap longer than
    /// `max_gap_s` resets.
    #[test]
    fn the_first_line_after_a_gap_is_checked_against_the_fulcrum() {
        use crate::trocar::GapOutcome;
        let f = Vector3::new(0.30, -0.02, 0.05);
        let lines = cone_swing(&f, 3.0, |t| 0.12 + 0.01 * (2.0 * core::f64::consts::PI * 0.3 * t).sin());
        let inside = |d: &mut Detector| {
            for l in &lines {
                d.step(l);
            }
            assert!(d.step(&lines[lines.len() - 1]).state.is_inside());
        };
        // Consistent after a 20 ms gap: stays inside.
        let mut d = fast(FastConfig::default());
        inside(&mut d);
        assert_eq!(d.resume_after_gap(20), GapOutcome::Resumed);
        assert!(d.step(&lines[lines.len() - 1]).state.is_inside());
        // Moved 1 cm sideways during the gap: outside on the first sample.
        let mut d = fast(FastConfig::default());
        inside(&mut d);
        let l = lines[lines.len() - 1];
        let moved = LineSample::new(l.wrist_base_m + Vector3::new(0.01, 0.0, 0.0), l.axis_base);
        // Without a gap, one such sample is not enough (extraction needs 10 ms of evidence) ...
        let mut e = d.clone();
        assert!(e.step(&moved).state.is_inside());
        // ... after a gap it is.
        assert_eq!(d.resume_after_gap(30), GapOutcome::Resumed);
        assert!(!d.step(&moved).state.is_inside(), "the line left the fulcrum during the gap");
        // Longer than max_gap_s (50 ms): reset.
        let mut d = fast(FastConfig::default());
        inside(&mut d);
        assert_eq!(d.resume_after_gap(51), GapOutcome::Reset);
        assert!(!d.step(&lines[lines.len() - 1]).state.is_inside());
    }

    #[test]
    fn known_instrument_length_makes_axial_extraction_immediate() {
        // Inside, then the surgeon pulls straight out along the axis: no lateral motion at all.
        let f = Vector3::new(0.42, 0.0, 0.02);
        let (mut lines, _, _) = scripted(&[f], 1, 0.0, 5.0);
        let axis = lines.last().unwrap().axis_base;
        let depth_at_end = (f - lines.last().unwrap().wrist_base_m).dot(&axis);
        let length = 0.30; // tip 0.30 m from the wrist: beyond the fulcrum while depth < 0.30
        let pull_start = lines.len();
        for k in 1..=1500 {
            lines.push(line_through(&f, &axis, depth_at_end + 0.0001 * k as f64)); // 0.1 m/s outwards
        }
        let tip_out_sample = pull_start + ((length - depth_at_end) / 0.0001).ceil() as usize - 1;
        for (length_known, must_detect) in [(Some(length), true), (None, false)] {
            let cfg = DetectorConfig {
                fast: FastConfig { instrument_length_m: length_known, ..Default::default() },
                ..Default::default()
            };
            let mut d = Detector::new(&cfg).unwrap();
            let mut out_at = None;
            for (i, l) in lines.iter().enumerate() {
                let e = d.step(l);
                if i >= pull_start && !e.state.is_inside() && out_at.is_none() {
                    out_at = Some(i);
                }
                if i == pull_start - 1 {
                    assert!(e.state.is_inside());
                }
            }
            match (must_detect, out_at) {
                (true, Some(i)) => {
                    let delay_s = (i as f64 - tip_out_sample as f64) * 0.001;
                    assert!((0.0..0.05).contains(&delay_s), "tip-over-fulcrum extraction delay {delay_s} s");
                }
                (false, None) => {} // without the length, an axial pull is invisible: no lines disagree
                (m, o) => panic!("length {length_known:?}: expected detection {m}, got {o:?}"),
            }
        }
    }

    #[test]
    fn trocar_memory_recognises_a_reinsertion_quickly() {
        let trocars = [Vector3::new(0.42, -0.08, 0.02), Vector3::new(0.48, 0.06, 0.04)];
        // Visit A, B, A, B: the second visits are re-insertions into known trocars.
        let (lines, phases, _) = scripted(&trocars, 4, 3.0, 8.0);
        let delays_for = |memory: bool| {
            let cfg = DetectorConfig {
                fast: FastConfig { trocar_memory: memory, instrument_length_m: Some(0.30), ..Default::default() },
                ..Default::default()
            };
            let mut d = Detector::new(&cfg).unwrap();
            let mut delays = Vec::new();
            let mut start = 0;
            let mut ids = Vec::new();
            let mut waiting = false;
            for (i, l) in lines.iter().enumerate() {
                if i > 0 && phases[i] != phases[i - 1] && phases[i] == Phase::Inside {
                    start = i;
                    waiting = true;
                }
                let e = d.step(l);
                if let (true, crate::trocar::TrocarState::Inside { id }) = (waiting, e.state) {
                    delays.push((i - start) as f64 * 0.001);
                    ids.push(id);
                    waiting = false;
                }
            }
            (delays, ids)
        };
        let (with, ids) = delays_for(true);
        let (without, _) = delays_for(false);
        assert_eq!(with.len(), 4);
        assert_eq!(ids[0], ids[2], "re-insertion into A must get A's id");
        assert_eq!(ids[1], ids[3], "re-insertion into B must get B's id");
        assert_ne!(ids[0], ids[1]);
        for k in 2..4 {
            assert!(with[k] <= 0.1, "re-insertion {k} took {} s with memory", with[k]);
            assert!(with[k] < without[k], "memory must speed re-insertion {k}: {} vs {}", with[k], without[k]);
        }
    }
}
