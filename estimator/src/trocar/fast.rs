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
